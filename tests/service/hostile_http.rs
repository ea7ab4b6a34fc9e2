//! Hostile HTTP against a running `coordinator serve`, over raw TCP on
//! loopback: malformed requests on every route cannot stop the service;
//! a page elsewhere cannot reach it (`Host`) nor change its state
//! (`Origin`); a token in a URL opens the event stream and nothing else.
//!
//! Every request is seeded (the same on every run), bounded in count and
//! each answered or closed within 10 s.

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use crate::support::*;

const TOKEN: &str = "s3cret";

/// A service on a free loopback port without local workers, with `extra`
/// flags (`crate::support::service::serve_without_workers`); returns it, its port and its scratch
/// directory once it serves.
fn serve(name: &str, extra: &[&str]) -> (Running, u16, std::path::PathBuf) {
    let dir = scratch(name);
    let (serve, url) =
        crate::support::service::serve_without_workers(&dir.join("data"), &dir, extra);
    let port = url
        .rsplit(':')
        .next()
        .and_then(|p| p.parse().ok())
        .expect("the service's port");
    (serve, port, dir)
}

/// What came back for one raw HTTP/1 request: the status, the head (in
/// lower case) and the body as far as it arrived.
struct Answer {
    status: u16,
    head: String,
    body: String,
}

/// Writes `request` to the service on `port` and reads the answer's head
/// (and the body, unless it is an event stream) within 10 s; `None` when
/// the service closed the connection without an HTTP/1 answer. With
/// `half_close` the writing side is closed after the request, so that a
/// request short of its body ends (the service may then drop the request
/// unanswered: the client went away).
fn send(port: u16, request: &[u8], half_close: bool) -> Result<Option<Answer>, String> {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).map_err(|e| e.to_string())?;
    s.set_read_timeout(Some(Duration::from_secs(10)))
        .map_err(|e| e.to_string())?;
    // The service may close first (a request it refuses outright).
    let _ = s.write_all(request);
    if half_close {
        let _ = s.shutdown(std::net::Shutdown::Write);
    }
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut answer = Vec::new();
    let mut buf = [0u8; 16 * 1024];
    loop {
        let head_end = answer.windows(4).position(|w| w == b"\r\n\r\n");
        if let Some(end) = head_end {
            let head = String::from_utf8_lossy(&answer[..end]).to_ascii_lowercase();
            // An event stream does not end: its head is the answer.
            if head.contains("text/event-stream") {
                break;
            }
        }
        if answer.len() > 1 << 20 {
            break;
        }
        match s.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => answer.extend_from_slice(&buf[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::ConnectionReset | std::io::ErrorKind::BrokenPipe
                ) =>
            {
                break;
            }
            Err(e) => return Err(format!("no answer within 10 s: {e}")),
        }
        if Instant::now() > deadline {
            return Err("no answer within 10 s".into());
        }
    }
    // Nothing, or HTTP/2's frames (its SETTINGS and GOAWAY to a preface
    // followed by garbage): no HTTP/1 answer.
    if !answer.starts_with(b"HTTP/") {
        return Ok(None);
    }
    let text = String::from_utf8_lossy(&answer).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head
        .strip_prefix("HTTP/1.1 ")
        .or_else(|| head.strip_prefix("HTTP/1.0 "))
        .and_then(|r| r.get(..3))
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| format!("no status line: {text:?}"))?;
    Ok(Some(Answer {
        status,
        head: head.to_ascii_lowercase(),
        body: body.to_string(),
    }))
}

/// A well-formed request: `method path`, `Host`, the extra header lines and the body.
fn request(method: &str, target: &str, host: &str, headers: &[&str], body: &str) -> Vec<u8> {
    let mut r = format!("{method} {target} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n");
    for h in headers {
        r.push_str(h);
        r.push_str("\r\n");
    }
    if !body.is_empty() || method == "POST" {
        r.push_str(&format!("Content-Length: {}\r\n", body.len()));
    }
    r.push_str("\r\n");
    r.push_str(body);
    r.into_bytes()
}

/// The status of a well-formed request; panics without an answer.
fn status(port: u16, method: &str, target: &str, host: &str, headers: &[&str]) -> u16 {
    answer(port, method, target, host, headers, "").status
}

fn answer(
    port: u16,
    method: &str,
    target: &str,
    host: &str,
    headers: &[&str],
    body: &str,
) -> Answer {
    send(port, &request(method, target, host, headers, body), false)
        .unwrap_or_else(|e| panic!("{method} {target}: {e}"))
        .unwrap_or_else(|| panic!("{method} {target}: closed without an answer"))
}

/// Whether the service still answers: `GET /metrics` (with the token) is
/// 200; what came instead.
fn answers(port: u16) -> Result<(), String> {
    let bearer = format!("Authorization: Bearer {TOKEN}");
    match send(
        port,
        &request("GET", "/metrics", "127.0.0.1", &[bearer.as_str()], ""),
        false,
    )? {
        Some(a) if a.status == 200 => Ok(()),
        Some(a) => Err(format!("{} {}", a.status, a.body)),
        None => Err("closed without an answer".into()),
    }
}

fn alive(port: u16) -> bool {
    answers(port).is_ok()
}

/// The one packet that stopped the service: `%` followed within two bytes
/// by a character of several bytes, in the studio's query token. It is
/// refused with a 4xx, and the service goes on.
#[test]
fn a_percent_before_a_multibyte_character_is_refused_and_the_service_lives() {
    let (mut serve, port, data) = serve("hostile-percent", &["--token", TOKEN]);
    for target in [
        "/studio/events?token=%a\u{e9}xx",
        "/studio/events?token=%\u{e9}",
        "/studio/scene?token=%a\u{e9}xx",
    ] {
        // The raw bytes (é as UTF-8), as a hostile client sends them.
        let packet = format!("GET {target} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
        let answer = send(port, packet.as_bytes(), false)
            .unwrap_or_else(|e| panic!("{target}: {e}"))
            .unwrap_or_else(|| panic!("{target}: closed without an answer"));
        assert!(
            (400..500).contains(&answer.status),
            "{target}: {} {}",
            answer.status,
            answer.body
        );
        assert!(alive(port), "the service died after {target}");
    }
    assert!(
        serve.child.try_wait().unwrap().is_none(),
        "the process lives"
    );
    serve.signal(15);
    let (status, log) = serve.finish(30);
    assert!(status.success(), "{}", log.join("\n"));
    assert!(
        !log.iter().any(|l| l.contains("panicked")),
        "{}",
        log.join("\n")
    );
    std::fs::remove_dir_all(&data).unwrap();
}

/// A seeded generator (SplitMix64): the same requests on every run.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }

    fn chance(&mut self, percent: u64) -> bool {
        self.next() % 100 < percent
    }

    fn pick<T: Copy>(&mut self, items: &[T]) -> T {
        items[self.below(items.len())]
    }

    fn bytes(&mut self, max: usize) -> Vec<u8> {
        let n = self.below(max + 1);
        (0..n).map(|_| self.next() as u8).collect()
    }

    /// Bytes that fit in a request line or a header value (no space, CR, LF).
    fn line_bytes(&mut self, max: usize) -> Vec<u8> {
        self.bytes(max)
            .into_iter()
            .map(|b| {
                if matches!(b, b' ' | b'\r' | b'\n') {
                    b'x'
                } else {
                    b
                }
            })
            .collect()
    }

    /// Visible ASCII and bytes of 128 and above (which are not UTF-8 alone):
    /// what a parser passes on to the service.
    fn visible_bytes(&mut self, max: usize) -> Vec<u8> {
        self.bytes(max)
            .into_iter()
            .map(|b| if b <= b' ' || b == 0x7f { b'%' } else { b })
            .collect()
    }

    /// Mostly visible bytes, now and then any byte but space, CR and LF.
    fn field_bytes(&mut self, max: usize) -> Vec<u8> {
        if self.chance(15) {
            self.line_bytes(max)
        } else {
            self.visible_bytes(max)
        }
    }
}

/// Every route of the service: the API, `/metrics`, the studio's page and
/// data routes, and the nine gRPC methods.
const ROUTES: &[&str] = &[
    "/",
    "/studio/studio.js",
    "/studio/studio.css",
    "/studio/scene",
    "/studio/save",
    "/studio/events",
    "/studio/tiles",
    "/api/v1/jobs",
    "/api/v1/jobs/1",
    "/api/v1/jobs/1/cancel",
    "/api/v1/workers",
    "/api/v1/openapi.json",
    "/metrics",
    "/hypertexture.v1.Farm/Register",
    "/hypertexture.v1.Farm/GetWork",
    "/hypertexture.v1.Farm/SubmitTile",
    "/hypertexture.v1.Farm/SubmitTiles",
    "/hypertexture.v1.Farm/Heartbeat",
    "/hypertexture.v1.Farm/Goodbye",
    "/hypertexture.v1.Farm/ReportFailure",
    "/hypertexture.v1.Farm/Withdrawals",
    "/hypertexture.v1.Farm/GetAsset",
];

/// `%` sequences that are not two hexadecimal digits, or decode to bytes
/// that are not UTF-8.
const PERCENTS: &[&[u8]] = &[
    b"%",
    b"%a",
    b"%zz",
    b"%a\xc3\xa9xx",
    b"%\xc3\xa9",
    b"%\xe2\x82\xac",
    b"%ff%fe",
    b"%c3",
    b"%c3%28",
    b"%00",
    b"%%%",
    b"%2",
    b"\xff\xfe",
    b"\xc3",
];

/// One malformed request for the service on `port` (`token`: whether it has one).
fn hostile(rng: &mut Rng, port: u16) -> Vec<u8> {
    let mut r: Vec<u8> = Vec::new();
    // Now and then, not HTTP at all (or HTTP/2's preface and then garbage).
    match rng.below(40) {
        0 => return rng.bytes(300),
        1 => {
            let mut v = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
            v.extend(rng.bytes(200));
            return v;
        }
        _ => {}
    }
    let method: &[u8] = match rng.below(20) {
        0..=8 => b"GET",
        9..=15 => b"POST",
        16 | 17 => rng.pick(&[&b"PUT"[..], b"DELETE", b"PATCH", b"HEAD", b"OPTIONS"]),
        18 => b"BREW",
        _ => &[b'G', 0xc3, 0xa9, b'T'],
    };
    r.extend_from_slice(method);
    r.push(b' ');
    r.extend_from_slice(rng.pick(ROUTES).as_bytes());
    match rng.below(8) {
        0 => r.extend(rng.field_bytes(20)),
        1 => r.extend_from_slice(rng.pick(PERCENTS)),
        2 => {
            r.push(b'/');
            r.extend_from_slice(rng.pick(PERCENTS));
        }
        _ => {}
    }
    if rng.chance(60) {
        r.push(b'?');
        for i in 0..rng.below(4) + 1 {
            if i > 0 {
                r.push(b'&');
            }
            let key: &[u8] = rng.pick(&[&b"token"[..], b"generation", b"from", b"to", b"x"]);
            r.extend_from_slice(key);
            if rng.chance(90) {
                r.push(b'=');
            }
            match rng.below(5) {
                0 => r.extend_from_slice(TOKEN.as_bytes()),
                1 => r.extend_from_slice(rng.pick(PERCENTS)),
                2 => r.extend(rng.field_bytes(12)),
                3 => r.extend_from_slice(rng.next().to_string().as_bytes()),
                _ => {
                    r.extend_from_slice(rng.pick(PERCENTS));
                    r.extend_from_slice(TOKEN.as_bytes());
                }
            }
        }
    }
    r.extend_from_slice(if rng.chance(95) {
        b" HTTP/1.1\r\n"
    } else {
        b" HTTP/9.9\r\n"
    });
    let host = match rng.below(16) {
        0 => None,
        1 => Some(rng.field_bytes(20)),
        2 => Some(b"localhost".to_vec()),
        3 => Some(format!("evil.example:{port}").into_bytes()),
        _ => Some(format!("127.0.0.1:{port}").into_bytes()),
    };
    if let Some(host) = host {
        r.extend_from_slice(b"Host: ");
        r.extend(host);
        r.extend_from_slice(b"\r\n");
    }
    match rng.below(6) {
        0 | 1 => r.extend_from_slice(format!("Authorization: Bearer {TOKEN}\r\n").as_bytes()),
        2 => r.extend_from_slice(format!("Authorization: bEaReR {TOKEN}\r\n").as_bytes()),
        3 => {
            r.extend_from_slice(b"Authorization: ");
            r.extend(rng.field_bytes(30));
            r.extend_from_slice(b"\r\n");
        }
        _ => {}
    }
    let content_type: &[u8] = rng.pick(&[
        &b"application/json"[..],
        b"application/grpc",
        b"application/grpc+proto",
        b"application/x-www-form-urlencoded",
        b"text/plain",
        b"multipart/form-data; boundary=\xff",
        b"",
    ]);
    if !content_type.is_empty() {
        r.extend_from_slice(b"Content-Type: ");
        r.extend_from_slice(content_type);
        r.extend_from_slice(b"\r\n");
    }
    if rng.chance(20) {
        r.extend_from_slice(b"Origin: ");
        r.extend_from_slice(rng.pick(&[
            &b"http://evil.example"[..],
            b"null",
            b"http://127.0.0.1",
            b"\xff",
        ]));
        r.extend_from_slice(b"\r\n");
    }
    for _ in 0..rng.below(3) {
        let name: &[u8] = rng.pick(&[&b"X-Junk"[..], b"Te", b"Accept", b"Cookie", b"Range"]);
        r.extend_from_slice(name);
        r.extend_from_slice(b": ");
        r.extend(rng.field_bytes(40));
        r.extend_from_slice(b"\r\n");
    }
    if rng.chance(3) {
        // A raw byte where a header line should be.
        r.extend(rng.bytes(20));
        r.extend_from_slice(b"\r\n");
    }
    let body: Vec<u8> = match rng.below(6) {
        0 => Vec::new(),
        1 => rng.bytes(400),
        2 => br#"{"scene": 7, "out": ["#.to_vec(),
        3 => br#"{"text": "(", "quality": "high", "knobs": {"x": 1e999}}"#.to_vec(),
        4 => {
            let mut b = br#"{"scene": ""#.to_vec();
            b.extend_from_slice(rng.pick(PERCENTS));
            b.extend_from_slice(br#"", "out": "x.png"}"#);
            b
        }
        _ => vec![0, 0, 0, 0, 5, 1, 2, 3, 4, 5],
    };
    match rng.below(8) {
        0 => r.extend_from_slice(b"Transfer-Encoding: chunked\r\n"),
        1 => r.extend_from_slice(format!("Content-Length: {}\r\n", body.len() + 7).as_bytes()),
        2 => r.extend_from_slice(b"Content-Length: -1\r\n"),
        _ => r.extend_from_slice(format!("Content-Length: {}\r\n", body.len()).as_bytes()),
    }
    if rng.chance(70) {
        r.extend_from_slice(b"Connection: close\r\n");
    }
    r.extend_from_slice(b"\r\n");
    r.extend(body);
    r
}

/// 3,000 seeded malformed requests over every route (2,000 to a service
/// with a token, half of them carrying it; 1,000 to one without): the
/// service answers every one (or closes the connection) within 10 s, never
/// with a 5xx, and still answers afterwards.
#[test]
fn seeded_malformed_requests_on_every_route_cannot_stop_the_service() {
    for (name, count, extra) in [
        ("hostile-token", 2000, &["--token", TOKEN][..]),
        ("hostile-open", 1000, &[][..]),
    ] {
        let (mut serve, port, data) = serve(name, extra);
        let mut rng = Rng(0x4854_5450 + count as u64);
        let started = Instant::now();
        let mut statuses: std::collections::BTreeMap<String, usize> = Default::default();
        let mut failures = Vec::new();
        for i in 0..count {
            let r = hostile(&mut rng, port);
            match send(port, &r, true) {
                Ok(Some(a)) => {
                    *statuses.entry(a.status.to_string()).or_default() += 1;
                    // 505 is hyper's answer to `HTTP/9.9`, the right one.
                    if a.status >= 500 && a.status != 505 {
                        failures.push(format!(
                            "{:?}: {} {}",
                            String::from_utf8_lossy(&r[..r.len().min(200)]),
                            a.status,
                            a.body
                        ));
                    }
                }
                Ok(None) => *statuses.entry("no HTTP/1 answer".into()).or_default() += 1,
                Err(e) => failures.push(format!(
                    "{:?}: {e}",
                    String::from_utf8_lossy(&r[..r.len().min(200)])
                )),
            }
            if i % 100 == 99
                && let Err(e) = answers(port)
            {
                let running = serve.child.try_wait().unwrap().is_none();

                let log: Vec<String> = serve.lines.try_iter().collect();
                panic!(
                    "{name}: the service stopped answering after request {i} (running: \
                     {running}; {e}): {:?}\nlog:\n{}",
                    String::from_utf8_lossy(&r[..r.len().min(200)]),
                    log.join("\n")
                );
            }
            assert!(
                started.elapsed() < Duration::from_secs(240),
                "{name}: {i} requests took 4 minutes"
            );
        }
        eprintln!(
            "{name}: {count} requests in {:.2} s: {statuses:?}",
            started.elapsed().as_secs_f64()
        );
        assert!(alive(port), "{name}: the service answers afterwards");
        assert!(
            serve.child.try_wait().unwrap().is_none(),
            "{name}: it lives"
        );
        serve.signal(15);
        let (status, log) = serve.finish(30);
        assert!(
            failures.is_empty(),
            "{name}: {} failures:\n{}\nlog:\n{}",
            failures.len(),
            failures.join("\n"),
            log.join("\n")
        );
        assert!(status.success(), "{}", log.join("\n"));
        assert!(
            !log.iter().any(|l| l.contains("panicked")),
            "{}",
            log.join("\n")
        );
        std::fs::remove_dir_all(&data).unwrap();
    }
}

/// Without a token only loopback names and `--allow-host` names are
/// served (DNS rebinding reaches nothing); a foreign `Origin` cannot change
/// state, token or not; the service's own clients are unaffected.
#[test]
fn a_page_elsewhere_can_neither_reach_nor_drive_the_service() {
    let (open, port, data) = serve("hostile-hosts", &["--allow-host", "Farm.LAN"]);
    let local = format!("127.0.0.1:{port}");
    for host in [
        local.clone(),
        "127.0.0.1".into(),
        format!("localhost:{port}"),
        format!("[::1]:{port}"),
        format!("farm.lan:{port}"),
    ] {
        assert_eq!(
            status(port, "GET", "/api/v1/jobs", &host, &[]),
            200,
            "{host}"
        );
    }
    for target in ["/api/v1/jobs", "/metrics", "/studio/scene", "/"] {
        let a = answer(
            port,
            "GET",
            target,
            &format!("rebound.example:{port}"),
            &[],
            "",
        );
        assert_eq!(a.status, 403, "{target}: {}", a.body);
        let error: serde_json::Value = serde_json::from_str(&a.body).unwrap();
        let error = error["error"].as_str().unwrap();
        assert!(
            error.contains("rebound.example") && error.contains("--allow-host rebound.example"),
            "{error}"
        );
    }
    // A gRPC call under a foreign name gets a gRPC refusal.
    let a = answer(
        port,
        "POST",
        "/hypertexture.v1.Farm/Heartbeat",
        "rebound.example",
        &["Content-Type: application/grpc", "TE: trailers"],
        "",
    );
    assert!(a.head.contains("grpc-status: 7"), "{}", a.head);

    // Cross-site form posts: cancel a job, save the studio's scene.
    let form = "Content-Type: application/x-www-form-urlencoded";
    for target in ["/api/v1/jobs/1/cancel", "/studio/save", "/studio/scene"] {
        let a = answer(
            port,
            "POST",
            target,
            &local,
            &[form, "Origin: http://evil.example"],
            "a=1",
        );
        assert_eq!(a.status, 403, "{target}: {}", a.body);
        assert!(a.body.contains("Origin"), "{}", a.body);
    }
    let own = format!("Origin: http://{local}");
    // From the service's own page, or with no Origin (the CLI), the route answers.
    assert_eq!(
        status(port, "POST", "/api/v1/jobs/1/cancel", &local, &[&own]),
        404
    );
    assert_eq!(
        status(port, "POST", "/api/v1/jobs/1/cancel", &local, &[]),
        404
    );
    // The CLI client (ureq) still works.
    let out = coordinator(&["status", "--server", &format!("http://{local}")]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    open.signal(15);
    open.finish(30);
    std::fs::remove_dir_all(&data).unwrap();

    // With a token any Host is served to its holder, and Origin still counts.
    let (closed, port, data) = serve("hostile-hosts-token", &["--token", TOKEN]);
    let bearer = format!("Authorization: Bearer {TOKEN}");
    assert_eq!(
        status(port, "GET", "/api/v1/jobs", "farm.example", &[&bearer]),
        200
    );
    let a = answer(
        port,
        "POST",
        "/api/v1/jobs/1/cancel",
        "127.0.0.1",
        &[&bearer, "Origin: http://evil.example"],
        "",
    );
    assert_eq!(a.status, 403, "{}", a.body);
    closed.signal(15);
    closed.finish(30);
    std::fs::remove_dir_all(&data).unwrap();
}

/// A query token opens `GET /studio/events` and no other route; the
/// bearer scheme is read in any case by the API, the studio and gRPC alike.
#[test]
fn a_url_token_opens_the_event_stream_only_and_bearer_is_case_insensitive() {
    let (serve, port, data) = serve("hostile-tokens", &["--token", TOKEN]);
    let host = "127.0.0.1";
    let events = answer(
        port,
        "GET",
        &format!("/studio/events?token={TOKEN}"),
        host,
        &[],
        "",
    );
    assert_eq!(events.status, 200, "{}", events.body);
    for (method, target) in [
        ("GET", "/studio/scene"),
        ("POST", "/studio/save"),
        ("POST", "/studio/scene"),
        ("GET", "/studio/tiles?generation=0&from=0&to=0"),
        ("GET", "/api/v1/jobs"),
        ("GET", "/metrics"),
    ] {
        let joined = if target.contains('?') { '&' } else { '?' };
        let target = format!("{target}{joined}token={TOKEN}");
        let a = answer(port, method, &target, host, &[], "");
        assert_eq!(a.status, 401, "{method} {target}: {}", a.body);
    }
    for scheme in ["Bearer", "bearer", "BEARER"] {
        let h = format!("Authorization: {scheme} {TOKEN}");
        for target in ["/studio/scene", "/api/v1/jobs", "/metrics"] {
            assert_eq!(
                status(port, "GET", target, host, &[&h]),
                200,
                "{h} {target}"
            );
        }
    }
    // gRPC: a lower-case scheme is the token too (an unknown worker's
    // heartbeat is refused for that, not for the token).
    let code = block_on(async {
        let mut client = hypertexture_proto::pb::farm_client::FarmClient::connect(format!(
            "http://127.0.0.1:{port}"
        ))
        .await
        .expect("connects");
        let mut request = tonic::Request::new(hypertexture_proto::pb::HeartbeatParams {
            worker_id: "w1-nobody".into(),
        });
        request
            .metadata_mut()
            .insert("authorization", format!("bearer {TOKEN}").parse().unwrap());
        client
            .heartbeat(request)
            .await
            .map(|_| ())
            .unwrap_err()
            .code()
    });
    assert_ne!(code, tonic::Code::Unauthenticated);
    serve.signal(15);
    serve.finish(30);
    std::fs::remove_dir_all(&data).unwrap();
}
