//! A headless Chromium and one page, spoken to over the DevTools protocol
//! (over `--remote-debugging-pipe`: JSON messages separated by NUL bytes on
//! file descriptors 3 and 4, no WebSocket needed). Every answer is awaited at
//! most 60 s; the browser is killed when its handle drops. Each test gives it
//! a profile directory of its own.

use std::io::{BufRead, BufReader, Write};
use std::os::fd::AsRawFd;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::{Value, json};

/// Chromium (`/usr/bin/chromium`, or `$CHROMIUM`), if installed.
pub fn chromium() -> Option<PathBuf> {
    let path = std::env::var_os("CHROMIUM")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/usr/bin/chromium"));
    path.is_file().then_some(path)
}

/// A headless Chromium and one page, spoken to over the DevTools pipe.
pub struct Browser {
    pub child: Child,
    to: std::io::PipeWriter,
    replies: mpsc::Receiver<Value>,
    next_id: u64,
    session: String,
}

impl Browser {
    pub fn start(binary: &Path, profile: &Path) -> Browser {
        // Chromium reads commands from fd 3 and writes replies to fd 4.
        let (commands_r, commands_w) = std::io::pipe().expect("pipe");
        let (replies_r, replies_w) = std::io::pipe().expect("pipe");
        let (cr, rw) = (commands_r.as_raw_fd(), replies_w.as_raw_fd());
        let mut command = Command::new(binary);
        command
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--disable-dev-shm-usage",
                "--remote-debugging-pipe",
                "--window-size=1400,900",
            ])
            .arg(format!("--user-data-dir={}", profile.display()))
            .arg("about:blank")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        // SAFETY: only async-signal-safe calls (fcntl, dup2) between fork and exec.
        unsafe {
            command.pre_exec(move || {
                // Out of the way of 3 and 4 first, then onto them (dup2
                // clears close-on-exec).
                let a = libc::fcntl(cr, libc::F_DUPFD, 10);
                let b = libc::fcntl(rw, libc::F_DUPFD, 10);
                if a < 0 || b < 0 || libc::dup2(a, 3) < 0 || libc::dup2(b, 4) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = command.spawn().expect("chromium starts");
        drop((commands_r, replies_w));
        let (tx, replies) = mpsc::channel();
        std::thread::spawn(move || {
            let mut reader = BufReader::new(replies_r);
            let mut message = Vec::new();
            while reader.read_until(0, &mut message).is_ok_and(|n| n > 0) {
                if message.last() == Some(&0) {
                    message.pop();
                }
                if let Ok(v) = serde_json::from_slice::<Value>(&message)
                    && tx.send(v).is_err()
                {
                    break;
                }
                message.clear();
            }
        });
        let mut browser = Browser {
            child,
            to: commands_w,
            replies,
            next_id: 1,
            session: String::new(),
        };
        let target = browser.call("Target.createTarget", json!({ "url": "about:blank" }));
        let attached = browser.call(
            "Target.attachToTarget",
            json!({ "targetId": target["targetId"], "flatten": true }),
        );
        browser.session = attached["sessionId"].as_str().expect("a session").into();
        browser.call("Page.enable", json!({}));
        browser.call("Runtime.enable", json!({}));
        browser.call(
            "Emulation.setDeviceMetricsOverride",
            json!({ "width": 1400, "height": 900, "deviceScaleFactor": 1, "mobile": false }),
        );
        browser
    }

    /// Sends a command (to the page once attached) and waits for its answer.
    pub fn call(&mut self, method: &str, params: Value) -> Value {
        match self.try_call(method, params) {
            Ok(result) => result,
            Err(reply) => panic!("{method}: {reply}"),
        }
    }

    /// [`Browser::call`], its error answer as `Err`.
    pub fn try_call(&mut self, method: &str, params: Value) -> Result<Value, Value> {
        let id = self.next_id;
        self.next_id += 1;
        let mut message = json!({ "id": id, "method": method, "params": params });
        if !self.session.is_empty() {
            message["sessionId"] = json!(self.session);
        }
        let mut bytes = serde_json::to_vec(&message).expect("json");
        bytes.push(0);
        self.to.write_all(&bytes).expect("chromium reads commands");
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let reply = self
                .replies
                .recv_timeout(left)
                .unwrap_or_else(|_| panic!("no answer to {method} within 60 s"));
            if reply["id"] == json!(id) {
                return match reply.get("error") {
                    Some(error) => Err(error.clone()),
                    None => Ok(reply["result"].clone()),
                };
            }
        }
    }

    /// The value of a JavaScript expression in the page.
    pub fn eval(&mut self, expression: &str) -> Value {
        let r = self.call(
            "Runtime.evaluate",
            json!({ "expression": expression, "returnByValue": true, "awaitPromise": true }),
        );
        assert!(
            r.get("exceptionDetails").is_none(),
            "{expression}: {}",
            r["exceptionDetails"]
        );
        r["result"]["value"].clone()
    }

    /// Waits (at most `secs`) until `expression` is true (once the page's
    /// script has run).
    pub fn wait_until(&mut self, expression: &str, secs: u64) {
        let deadline = Instant::now() + Duration::from_secs(secs);
        let guarded = format!("typeof studio !== 'undefined' && ({expression})");
        // Checked in the page every 20 ms for up to a second per call (no
        // round trip through the protocol per check: the browser shares the
        // cores with the workers being measured).
        let waiting = format!(
            "new Promise((done) => {{ const end = performance.now() + 1000; \
             const check = () => {{ let ok = false; try {{ ok = {guarded}; }} catch (e) {{}} \
             if (ok || performance.now() > end) done(ok === true); else setTimeout(check, 20); }}; check(); }})"
        );
        // A page replaced while the promise waits answers with an error: not yet.
        let holds = |b: &mut Browser| {
            b.try_call(
                "Runtime.evaluate",
                json!({ "expression": waiting, "returnByValue": true, "awaitPromise": true }),
            )
            .is_ok_and(|r| r["result"]["value"] == json!(true))
        };
        while !holds(self) {
            assert!(
                Instant::now() < deadline,
                "not true within {secs} s: {expression}; studio: {}",
                self.eval("JSON.stringify({...studio, view: null})")
            );
        }
    }

    /// The canvas's RGBA bytes.
    pub fn canvas(&mut self) -> Vec<u8> {
        self.canvas_of("image")
    }

    /// The RGBA pixels of the canvas with id `id`.
    pub fn canvas_of(&mut self, id: &str) -> Vec<u8> {
        let b64 = self.eval(&format!(
            "(() => {{ const c = document.getElementById('{id}'); \
             const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; \
             let s = ''; for (let i = 0; i < d.length; i++) s += String.fromCharCode(d[i]); \
             return btoa(s); }})()"
        ));
        use base64::Engine as _;
        base64::engine::general_purpose::STANDARD
            .decode(b64.as_str().expect("a string"))
            .expect("base64")
    }

    pub fn key(&mut self, key: &str, code: u32) {
        for kind in ["keyDown", "keyUp"] {
            self.call(
                "Input.dispatchKeyEvent",
                json!({ "type": kind, "key": key, "code": key, "windowsVirtualKeyCode": code }),
            );
        }
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Chromium for a test that needs it: without it the test is to skip (a
/// message says so), except in CI (`CI` set), where it fails:
/// `scripts/test-deps/chromium.sh` installs it.
pub fn chromium_or_skip() -> Option<PathBuf> {
    let found = chromium();
    if found.is_none() {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI needs Chromium at /usr/bin/chromium (or $CHROMIUM): scripts/test-deps/chromium.sh installs it"
        );
        eprintln!(
            "skipped: no Chromium at /usr/bin/chromium (or $CHROMIUM); run scripts/test-deps/chromium.sh"
        );
    }
    found
}
