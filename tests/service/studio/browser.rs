//! The studio's scene browser: `coordinator studio DIR` lists the
//! directory's scenes with thumbnails rendered by the farm (a broken scene
//! shows its error instead), opens one for every tab (a mesh scene with the
//! files it names), and refuses paths outside the directory and opens that
//! would lose unsaved edits.

use std::path::{Path, PathBuf};

use serde_json::{Value, json};

use super::{COMPLETE_HIGH, in_process, open_page, small_copy, studio, write_screenshot};
use crate::support::browser::{Browser, chromium_or_skip};
use crate::support::http::{self, Answer};
use crate::support::{Running, coordinator, root, scratch};

/// A directory of three scenes at 24 × 24 under `dir/scenes`: the noisy
/// sphere (first in path order), furry Spot with its mesh in `mesh/`, and a
/// scene that does not parse.
fn three_scenes(dir: &Path) -> PathBuf {
    let scenes = dir.join("scenes");
    std::fs::create_dir_all(scenes.join("mesh/meshes")).unwrap();
    let sphere = small_copy(&scenes, "scenes/noisy_sphere.ron", 24);
    std::fs::rename(sphere, scenes.join("a_noisy_sphere.ron")).unwrap();
    small_copy(&scenes.join("mesh"), "scenes/mesh/furry_spot.ron", 24);
    std::fs::copy(
        root().join("scenes/mesh/meshes/spot.obj"),
        scenes.join("mesh/meshes/spot.obj"),
    )
    .unwrap();
    std::fs::write(
        scenes.join("x_broken.ron"),
        "Scene(image: (width: 24, height: 24),\n  camera: oops,\n)\n",
    )
    .unwrap();
    scenes
}

/// `coordinator studio PATH` with 2 local workers: the studio, its URL and
/// port.
fn started(path: &Path, data: &Path) -> (Running, String, u16) {
    let mut studio = studio(path, data, 2);
    let port = studio.port();
    studio.wait_for("serving on", 30);
    (studio, format!("http://127.0.0.1:{port}"), port)
}

/// Scene `path`'s thumbnail, once ready: its PNG decoded.
fn thumbnail(url: &str, path: &str) -> image::RgbaImage {
    let mut response = ureq::get(&format!("{url}/studio/scenes/thumbnail?path={path}"))
        .call()
        .unwrap_or_else(|e| panic!("{path}'s thumbnail: {e}"));
    let png = response.body_mut().read_to_vec().unwrap();
    image::load_from_memory(&png).unwrap().to_rgba8()
}

fn post_raw(url: &str, path: &str, body: &str) -> Answer {
    http::answer(
        ureq::post(&format!("{url}{path}"))
            .config()
            .http_status_as_error(false)
            .build()
            .header("Content-Type", "application/json")
            .send(body),
    )
}

/// Waits in `browser` for scene `path` shown and drawn whole at high
/// quality after frame `generation`.
fn shown(browser: &mut Browser, path: &str, generation: &Value) {
    browser.wait_until(
        &format!(
            "studio.view.browser.path === {} && studio.generation > {generation} && {COMPLETE_HIGH}",
            json!(path)
        ),
        120,
    );
}

/// The text box's text, changed as typed (the page sends it).
fn type_text(browser: &mut Browser, text: &str) {
    browser.eval(&format!(
        "(() => {{ const t = document.getElementById('text'); t.value = {}; \
         t.dispatchEvent(new Event('input')); }})()",
        json!(text)
    ));
}

#[test]
fn the_browser_lists_thumbnails_and_opens_a_scene_in_every_tab() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let dir = scratch("studio-browser");
    let scenes = three_scenes(&dir);
    let sphere = scenes.join("a_noisy_sphere.ron");
    let spot = scenes.join("mesh/furry_spot.ron");
    let spot_text = std::fs::read_to_string(&spot).unwrap();
    std::fs::create_dir_all(dir.join("spot")).unwrap();
    let spot_reference = in_process(&spot, &dir.join("spot"));
    let sphere_reference = in_process(&sphere, &dir);
    let (mut studio, url, port) = started(&scenes, &dir.join("data"));

    // The first scene is live, the browser shown, the thumbnails load.
    let mut browser = open_page(&chromium, &dir, port);
    assert_eq!(browser.canvas(), sphere_reference, "the first scene opens");
    browser.call(
        "Emulation.setDeviceMetricsOverride",
        json!({ "width": 1280, "height": 800, "deviceScaleFactor": 1, "mobile": false }),
    );
    assert_eq!(
        browser.eval("document.getElementById('browser').hidden"),
        json!(false)
    );
    browser.wait_until(
        "Object.keys(studio.thumbnails).length === 2 && \
         [...document.querySelectorAll('#scene-list img')].filter((i) => i.complete && i.naturalWidth > 0).length === 2",
        120,
    );
    let listed = browser.eval(
        "[...document.querySelectorAll('#scene-list button.scene')].map((b) => b.dataset.path)",
    );
    assert_eq!(
        listed,
        json!(["a_noisy_sphere.ron", "mesh/furry_spot.ron", "x_broken.ron"])
    );
    let error = browser.eval(
        "document.querySelector('#scene-list button[data-path=\"x_broken.ron\"] .scene-error').textContent",
    );
    assert!(
        error
            .as_str()
            .unwrap()
            .contains("x_broken.ron:2:11: expected camera"),
        "the broken scene shows its error: {error}"
    );
    assert_eq!(
        browser.eval("document.querySelector('#scene-list button.live').dataset.path"),
        json!("a_noisy_sphere.ron")
    );
    for path in ["a_noisy_sphere.ron", "mesh/furry_spot.ron"] {
        let image = thumbnail(&url, path);
        assert_eq!(image.dimensions(), (24, 24), "{path}: the scene's own size");
        let first = image.get_pixel(0, 0);
        assert!(
            image.pixels().any(|p| p != first),
            "{path}'s thumbnail is not blank"
        );
    }
    let broken = http::get(&url, "/studio/scenes/thumbnail?path=x_broken.ron");
    assert_eq!(broken.status, 404, "{}", broken.body);
    // The image stays in view beside the browser.
    let boxes = browser.eval(
        "(() => { const i = document.getElementById('image').getBoundingClientRect(); \
         const b = document.getElementById('browser').getBoundingClientRect(); \
         return [i.top, i.bottom, i.right, b.left, innerHeight]; })()",
    );
    let [top, bottom, right, left, height] =
        [0, 1, 2, 3, 4].map(|i| boxes[i].as_f64().expect("the boxes"));
    assert!(
        top >= 0.0 && bottom <= height && right <= left,
        "the image is on screen, clear of the browser: {boxes}"
    );
    let shot = browser.call("Page.captureScreenshot", json!({ "format": "png" }));
    write_screenshot(&shot, &dir.join("scenes.png"));

    // A second tab follows the first one's open.
    let mut other = Browser::start(&chromium, &dir.join("profile-2"));
    other.call("Page.navigate", json!({ "url": format!("{url}/") }));
    other.wait_until(COMPLETE_HIGH, 120);
    let generation = browser.eval("studio.generation");
    browser.eval(
        "document.querySelector('#scene-list button[data-path=\"mesh/furry_spot.ron\"]').click()",
    );
    shown(&mut browser, "mesh/furry_spot.ron", &generation);
    assert_eq!(browser.canvas(), spot_reference, "the mesh scene's render");
    shown(&mut other, "mesh/furry_spot.ron", &generation);
    assert_eq!(other.canvas(), spot_reference, "the other tab follows");
    assert_eq!(
        other.eval("document.getElementById('text').value"),
        json!(spot_text)
    );
    assert!(
        other
            .eval("document.title")
            .as_str()
            .unwrap()
            .contains("furry_spot.ron")
    );
    assert_eq!(
        browser.eval("document.querySelector('#scene-list button.live').dataset.path"),
        json!("mesh/furry_spot.ron")
    );
    drop(other);

    saves_and_refuses_to_lose_edits(&mut browser, &url, &scenes, &sphere_reference);
    drop(browser);
    let _ = studio.child.kill();
    let _ = studio.child.wait();
}

/// Save writes the scene opened; opening another over unsaved edits is
/// refused until discarded.
fn saves_and_refuses_to_lose_edits(
    browser: &mut Browser,
    url: &str,
    scenes: &Path,
    sphere_reference: &[u8],
) {
    let spot = scenes.join("mesh/furry_spot.ron");
    let sphere_text = std::fs::read_to_string(scenes.join("a_noisy_sphere.ron")).unwrap();
    let edited = format!(
        "{}// saved from the browser\n",
        std::fs::read_to_string(&spot).unwrap()
    );
    type_text(browser, &edited);
    browser.wait_until(&format!("studio.view.text === {}", json!(edited)), 30);
    browser.eval("document.getElementById('save').click()");
    browser.wait_until(
        "/saved/.test(document.getElementById('action-result').textContent)",
        30,
    );
    assert_eq!(
        std::fs::read_to_string(&spot).unwrap(),
        edited,
        "saved to the scene opened"
    );
    assert!(scenes.join("mesh/furry_spot.ron.~1~").exists());
    assert_eq!(
        std::fs::read_to_string(scenes.join("a_noisy_sphere.ron")).unwrap(),
        sphere_text,
        "the scene before is untouched"
    );

    // Unsaved edits: refused (409), then opened with discard.
    let unsaved = format!("{edited}// not saved\n");
    type_text(browser, &unsaved);
    browser.wait_until(&format!("studio.view.text === {}", json!(unsaved)), 30);
    let refused = http::post(
        url,
        "/studio/open",
        &json!({ "path": "a_noisy_sphere.ron" }),
    );
    assert_eq!(refused.status, 409, "{}", refused.body);
    assert!(
        refused
            .error()
            .starts_with("unsaved edits to furry_spot.ron"),
        "{}",
        refused.body
    );
    let generation = browser.eval("studio.generation");
    browser.eval(
        "document.querySelector('#scene-list button[data-path=\"a_noisy_sphere.ron\"]').click()",
    );
    browser.wait_until("!document.getElementById('discard-open').hidden", 30);
    browser.eval("document.getElementById('discard-open').click()");
    shown(browser, "a_noisy_sphere.ron", &generation);
    assert_eq!(browser.canvas(), sphere_reference, "the sphere again");
    assert_eq!(
        browser.eval("[studio.view.undo, studio.view.redo, studio.view.snapshots.length]"),
        json!([0, 0, 0]),
        "history and snapshots belong to the scene"
    );
    assert_eq!(
        std::fs::read_to_string(&spot).unwrap(),
        edited,
        "the discarded edit is not written"
    );
}

/// Paths outside the directory, unknown scenes and malformed requests are
/// refused with their reason; a directory without scenes is a CLI error.
#[test]
fn the_browser_refuses_paths_outside_the_directory_and_bad_requests() {
    let dir = scratch("studio-browser-bad");
    let scenes = three_scenes(&dir);
    std::fs::write(dir.join("x.ron"), "Scene()").unwrap();
    std::os::unix::fs::symlink(dir.join("x.ron"), scenes.join("link.ron")).unwrap();
    let (mut studio, url, _) = started(&scenes, &dir.join("data"));

    let listing = http::get(&url, "/studio/scenes").json();
    let paths: Vec<&str> = listing["scenes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["path"].as_str().unwrap())
        .collect();
    assert_eq!(
        paths,
        ["a_noisy_sphere.ron", "mesh/furry_spot.ron", "x_broken.ron"],
        "a link out is not listed"
    );
    for (path, status, says) in [
        ("../x.ron", 400, "`../x.ron` is not a scene's path inside"),
        (
            "/etc/passwd",
            400,
            "`/etc/passwd` is not a scene's path inside",
        ),
        ("link.ron", 400, "`link.ron` leads outside"),
        ("nothing.ron", 404, "no scene `nothing.ron`"),
        ("notes.txt", 400, "not a scene"),
    ] {
        let open = http::post(&url, "/studio/open", &json!({ "path": path }));
        assert_eq!(open.status, status, "{path}: {}", open.body);
        assert!(open.error().contains(says), "{path}: {}", open.body);
    }
    let thumb = http::get(&url, "/studio/scenes/thumbnail?path=../x.ron");
    assert_eq!(thumb.status, 400, "{}", thumb.body);
    let thumb = http::get(&url, "/studio/scenes/thumbnail?path=nothing.ron");
    assert_eq!(thumb.status, 404, "{}", thumb.body);
    let thumb = http::get(&url, "/studio/scenes/thumbnail");
    assert_eq!(thumb.status, 400, "{}", thumb.body);
    for body in [
        "{",
        "[]",
        "{\"path\": 3}",
        "{\"path\": \"a.ron\", \"extra\": 1}",
    ] {
        let open = post_raw(&url, "/studio/open", body);
        assert_eq!(open.status, 400, "{body}: {}", open.body);
        assert!(!open.error().is_empty(), "{body}: {}", open.body);
    }
    let stale = http::post(
        &url,
        "/studio/open",
        &json!({ "path": "x_broken.ron", "base": 999 }),
    );
    assert_eq!(stale.status, 409, "{}", stale.body);
    // A broken scene opens with its error.
    let open = http::post(&url, "/studio/open", &json!({ "path": "x_broken.ron" }));
    assert_eq!(open.status, 200, "{}", open.body);
    let error = open.json()["error"]
        .as_str()
        .unwrap_or_default()
        .to_string();
    assert!(error.contains("x_broken.ron:2:11"), "{error}");
    let _ = studio.child.kill();
    let _ = studio.child.wait();

    // A studio on a file browses its directory, no page shown first.
    let (mut studio, url, _) = started(&scenes.join("mesh/furry_spot.ron"), &dir.join("data-2"));
    let view = http::get(&url, "/studio/scene").json();
    assert_eq!(view["browser"]["path"], json!("furry_spot.ron"));
    assert_eq!(view["browser"]["first"], json!(false));
    let _ = studio.child.kill();
    let _ = studio.child.wait();

    let empty = dir.join("empty");
    std::fs::create_dir_all(empty.join("sub")).unwrap();
    let out = coordinator(&["studio", empty.to_str().unwrap(), "--listen", "127.0.0.1:0"]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains(&format!("{}: no scenes", empty.display())),
        "{stderr}"
    );
}
