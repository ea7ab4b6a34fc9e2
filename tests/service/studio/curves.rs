//! The studio's curve editor and look controls, driven in headless Chromium:
//! a point added to a curve and one deleted, a curve's interpolation, a
//! colour stop's colour, a distortion term's switch and a 2D transfer
//! function's grid painted, each written into the scene's text through the
//! server's one state (and so one undo step each).

use std::path::{Path, PathBuf};

use serde_json::{Value, json};

use super::{
    COMPLETE_HIGH, element_png, open_page, small_copy, srgb_decode, studio, write_screenshot,
};
use crate::support::browser::{Browser, chromium_or_skip};
use crate::support::{Running, decode_png, in_process_file, scratch, until};

/// A studio on a copy of `scene` (from the repository's root) at 24 × 24 in
/// a scratch folder named `name`, and a page on it once its first frame is
/// drawn: the folder, the scene file, its text, the studio, its URL and the
/// page.
fn opened(
    chromium: &Path,
    name: &str,
    scene: &str,
) -> (PathBuf, PathBuf, String, Running, String, Browser) {
    let dir = scratch(name);
    let scene = small_copy(&dir, scene, 24);
    let original = std::fs::read_to_string(&scene).unwrap();
    let mut studio = studio(&scene, &dir.join("data"), 1);
    let port = studio.port();
    studio.wait_for("serving on", 30);
    let browser = open_page(chromium, &dir, port);
    let url = format!("http://127.0.0.1:{port}");
    (dir, scene, original, studio, url, browser)
}

fn view(url: &str) -> Value {
    crate::support::http::get(url, "/studio/scene").json()
}

fn text(url: &str) -> String {
    view(url)["text"].as_str().unwrap().to_string()
}

fn close(browser: Browser, mut studio: Running) {
    drop(browser);
    let _ = studio.child.kill();
    let _ = studio.child.wait();
}

/// The page's image differs from `before` and is byte for byte the
/// in-process render of the studio's text (written to `dir/edited.ron`).
fn changed_as_the_cli_renders(browser: &mut Browser, before: &[u8], dir: &Path, url: &str) {
    let after = browser.canvas();
    assert_ne!(after, before, "the image changes");
    let edited = dir.join("edited.ron");
    std::fs::write(&edited, text(url)).unwrap();
    let reference = dir.join("edited.png");
    in_process_file(&edited, &reference, &[]);
    assert_eq!(
        after,
        decode_png(&reference).into_raw(),
        "as the CLI renders it"
    );
}

/// Waits for the high-quality frame after frame `generation`.
fn rested(browser: &mut Browser, generation: &Value) {
    browser.wait_until(
        &format!("studio.generation > {generation} && {COMPLETE_HIGH}"),
        120,
    );
}

/// The page's curve `id`: its line's points and its handles' count.
fn drawn(browser: &mut Browser, id: &str) -> Value {
    browser.eval(&format!(
        "(() => {{ const s = document.getElementById({}); \
         return [s.querySelector('polyline')?.getAttribute('points') ?? '', \
                 s.querySelectorAll('circle').length]; }})()",
        serde_json::to_string(&format!("curve-{id}")).unwrap()
    ))
}

/// A point added to a curve by a double-click changes the scene's text (in
/// key order, in the list's layout) and the curve drawn; Ctrl+Z gives the
/// text back byte for byte; a point deleted with Delete point changes both
/// again. A screenshot of the editor in use is written beside the scene
/// (`curves.png`).
#[test]
fn a_point_added_and_one_deleted_change_the_text_and_the_drawn_curve_and_undo_restores_it() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let (dir, _, original, studio, url, mut browser) = opened(
        &chromium,
        "studio-curve-points",
        "scenes/gilet/craters_r0.ron",
    );
    let alpha = "alpha_map.points";
    let before = drawn(&mut browser, alpha);
    assert_eq!(before[1], 2, "two points: {before}");
    // A double-click at key 0.25, value 0.5 of the alpha map.
    let generation = browser.eval("studio.generation");
    browser.eval(
        "(() => { const s = document.getElementById('curve-alpha_map.points'); \
         s.scrollIntoView(); const r = s.getBoundingClientRect(); \
         const at = (x, y) => [r.left + (8 + x * 264) / 280 * r.width, \
                               r.top + (112 - y * 104) / 120 * r.height]; \
         const [clientX, clientY] = at(0.25, 0.5); \
         s.dispatchEvent(new MouseEvent('dblclick', { clientX, clientY, bubbles: true })); })()",
    );
    // The pointer's position is whole pixels: the value within a hundredth.
    let start = "alpha_map: (interpolation: Step, points: [(0.0, 0.0), (0.25, ";
    until(60, "the new point reaches the text", || {
        text(&url).contains(start)
    });
    let now = text(&url);
    let line = now.lines().find(|l| l.contains(start)).unwrap().trim();
    let y: f64 = line[start.len()..line.find("), (0.5, 1.0)]),").expect(line)]
        .parse()
        .expect(line);
    assert!((y - 0.5).abs() <= 0.02, "{line}");
    let added = format!("{start}{y:?}), (0.5, 1.0)]),");
    assert_eq!(
        now,
        original.replace(
            "alpha_map: (interpolation: Step, points: [(0.0, 0.0), (0.5, 1.0)]),",
            &added
        ),
        "only the alpha map's line changes"
    );
    browser.wait_until(
        "document.getElementById('curve-alpha_map.points').querySelectorAll('circle').length === 3",
        60,
    );
    rested(&mut browser, &generation);
    let after = drawn(&mut browser, alpha);
    assert_ne!(after[0], before[0], "the line is drawn anew");
    // The renderer's own values: 0.5 from the new key to the next.
    let values = |v: &Value| -> Vec<f64> {
        let c = v["curves"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["id"] == "alpha_map.points")
            .unwrap()
            .clone();
        c["values"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let sampled = values(&view(&url));
    assert!((sampled[90] - y).abs() < 1e-6, "at 0.375: {}", sampled[90]);
    let page =
        browser.eval("studio.view.curves.find((c) => c.id === 'alpha_map.points').values[90]");
    assert_eq!(
        page.as_f64(),
        Some(sampled[90]),
        "the page has the renderer's values"
    );
    // The editor in use: the curves, the grid and the distortion's controls.
    let rect = browser.eval(
        "(() => { const e = document.getElementById('curves'); e.scrollIntoView(); \
         const d = document.getElementById('distortions').getBoundingClientRect(); \
         const r = e.getBoundingClientRect(); \
         return [r.x + scrollX, r.y + scrollY, r.width, d.bottom - r.top]; })()",
    );
    let [x, y, w, h] = [0, 1, 2, 3].map(|i| rect[i].as_f64().expect("the editor's box"));
    let shot = browser.call(
        "Page.captureScreenshot",
        json!({ "format": "png", "captureBeyondViewport": true,
                "clip": { "x": x, "y": y, "width": w, "height": h, "scale": 1 } }),
    );
    write_screenshot(&shot, &dir.join("curves.png"));

    // Ctrl+Z, outside the text box: the text as opened, byte for byte.
    browser.eval("document.activeElement.blur()");
    for kind in ["keyDown", "keyUp"] {
        browser.call(
            "Input.dispatchKeyEvent",
            json!({ "type": kind, "key": "z", "code": "KeyZ",
                    "windowsVirtualKeyCode": 90, "modifiers": 2 }),
        );
    }
    until(30, "the undo reaches the server", || text(&url) == original);
    assert_eq!(text(&url).as_bytes(), original.as_bytes());
    browser.wait_until(
        &format!(
            "document.getElementById('text').value === {} && \
             document.getElementById('curve-alpha_map.points').querySelectorAll('circle').length === 2",
            serde_json::to_string(&original).unwrap()
        ),
        60,
    );
    assert_eq!(drawn(&mut browser, alpha), before, "the curve as it was");

    // The first point selected and deleted: the step from 0 to 1 at 0.5
    // is gone, the map is 1 everywhere.
    let generation = browser.eval("studio.generation");
    browser.eval(
        "(() => { document.getElementById('curve-alpha_map.points').querySelector('[data-point=\"0\"]').focus(); \
         document.getElementById('delete-alpha_map.points').click(); })()",
    );
    let deleted = "alpha_map: (interpolation: Step, points: [(0.5, 1.0)]),";
    until(60, "the deletion reaches the text", || {
        text(&url).contains(deleted)
    });
    browser.wait_until(
        "document.getElementById('curve-alpha_map.points').querySelectorAll('circle').length === 1",
        60,
    );
    rested(&mut browser, &generation);
    assert!(values(&view(&url)).iter().all(|&v| v == 1.0));
    assert_ne!(drawn(&mut browser, alpha)[0], before[0]);
    assert_eq!(
        (view(&url)["undo"].clone(), view(&url)["redo"].clone()),
        (json!(1), json!(0)),
        "the deletion is one step; the undone addition is gone from redo"
    );
    // A malformed or impossible edit is refused with the reason, and the
    // scene stays as it is.
    let shown = text(&url);
    for (edits, says) in [
        (
            json!([{ "op": "delete_point", "curve": alpha, "index": 0 }]),
            "one point left",
        ),
        (
            json!([{ "op": "set", "path": "alpha_map.interpolation", "to": "Cubic" }]),
            "`Cubic` is not one of",
        ),
        (json!([{ "op": "explode" }]), "unknown variant `explode`"),
        (
            json!([{ "op": "add_point", "curve": alpha }]),
            "missing field `x`",
        ),
    ] {
        let body = json!({ "quality": "high", "edits": edits });
        let answer = crate::support::http::post(&url, "/studio/scene", &body);
        assert_eq!(answer.status, 400, "{edits}: {}", answer.body);
        assert!(answer.error().contains(says), "{edits}: {}", answer.error());
    }
    assert_eq!(text(&url), shown);
    close(browser, studio);
}

/// The curve `id`'s picture (a screenshot of its frame), and the mean row of
/// its line in the column at key `at`, as a fraction of the frame's inner
/// height from the top (the frame is inset by 8 of 280 × 120 units).
fn line_at(browser: &mut Browser, id: &str) -> impl Fn(f64) -> f64 + use<> {
    let png = element_png(browser, &format!("curve-{id}"));
    let image = image::load_from_memory(&png).unwrap().to_rgba8();
    move |at: f64| {
        let (iw, ih) = (image.width() as f64, image.height() as f64);
        let px = ((8.0 + at * 264.0) / 280.0 * iw) as u32;
        let rows: Vec<f64> = (0..image.height())
            .filter(|&py| image.get_pixel(px, py).0[..3].iter().any(|&c| c > 0x80))
            .map(|py| ((py as f64 + 0.5) / ih * 120.0 - 8.0) / 104.0)
            .collect();
        assert!(!rows.is_empty(), "no line in column {at}");
        rows.iter().sum::<f64>() / rows.len() as f64
    }
}

/// A transfer function's interpolation switched from Linear (left to its
/// default) to Step is written beside its points and drawn as a step: read
/// from the page's pixels, 1 up to the second key and 0 past it, never the
/// V its three points make when linear.
#[test]
fn an_interpolation_switched_to_step_is_drawn_as_a_step() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let (_dir, _, original, studio, url, mut browser) = opened(
        &chromium,
        "studio-curve-step",
        "scenes/gilet/multi_blend_bumps.ron",
    );
    let id = "distortion.terms[0].transfer.Curve.points";
    let linear = line_at(&mut browser, id);
    let (low, high) = (linear(0.25), linear(0.75));
    assert!(
        (0.4..0.6).contains(&low) && (0.4..0.6).contains(&high),
        "a V: {low} {high}"
    );
    let generation = browser.eval("studio.generation");
    browser.eval(&format!(
        "(() => {{ const s = document.getElementById({}); s.value = 'Step'; \
         s.dispatchEvent(new Event('change')); }})()",
        serde_json::to_string(&format!("interp-{id}")).unwrap()
    ));
    let stepped = "(amplitude: 0.05, frequency: 6.0, shift: 0.5, transfer: Curve(interpolation: Step, points: [(0.0, 1.0), (0.5, 0.0), (1.0, 1.0)]), operator: Sum),";
    until(60, "the interpolation reaches the text", || {
        text(&url).contains(stepped)
    });
    assert_eq!(
        text(&url),
        original.replacen(
            "(amplitude: 0.05, frequency: 6.0, shift: 0.5, transfer: Curve(points: [(0.0, 1.0), (0.5, 0.0), (1.0, 1.0)]), operator: Sum),",
            stepped,
            1
        )
    );
    rested(&mut browser, &generation);
    browser.wait_until(
        &format!(
            "studio.view.curves.find((c) => c.id === {}).interpolation === 'Step'",
            serde_json::to_string(id).unwrap()
        ),
        30,
    );
    let step = line_at(&mut browser, id);
    let (low, high) = (step(0.25), step(0.75));
    assert!(
        low < 0.15,
        "1 below the second key (the V gives 0.5): {low}"
    );
    assert!(high > 0.85, "0 past it: {high}");
    assert_eq!(
        browser.eval(&format!(
            "document.getElementById({}).value",
            serde_json::to_string(&format!("interp-{id}")).unwrap()
        )),
        json!("Step")
    );
    close(browser, studio);
}

/// A colour map's stop selected and its colour picked: the stop's three
/// numbers in the text are the picked colour in linear light, nothing else
/// changes, and it is one undo step.
#[test]
fn a_colour_stop_picked_changes_the_text() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let (_dir, _, original, studio, url, mut browser) =
        opened(&chromium, "studio-curve-stop", "scenes/fur.ron");
    let generation = browser.eval("studio.generation");
    browser.eval(
        "(() => { document.getElementById('curve-colour_map.points').querySelector('[data-point=\"1\"]').focus(); \
         const p = document.getElementById('stop-colour_map.points'); \
         p.dispatchEvent(new PointerEvent('pointerdown', { bubbles: true })); \
         p.value = '#336699'; p.dispatchEvent(new Event('input')); \
         p.dispatchEvent(new PointerEvent('pointerup', { bubbles: true })); })()",
    );
    until(60, "the picked colour reaches the text", || {
        text(&url) != original
    });
    rested(&mut browser, &generation);
    let now = text(&url);
    let start = now.find("(0.5, (").expect("the second stop") + "(0.5, (".len();
    let end = start + now[start..].find(')').unwrap();
    let values: Vec<f64> = now[start..end]
        .split(',')
        .map(|v| v.trim().parse().unwrap())
        .collect();
    for (got, code) in values.iter().zip([0x33, 0x66, 0x99]) {
        let want = srgb_decode(f64::from(code) / 255.0);
        assert!(
            (got - want).abs() < 1e-5,
            "{}: {got} for #{code:02x}",
            &now[start..end]
        );
    }
    assert_eq!(
        format!("{}0.80, 0.62, 0.42{}", &now[..start], &now[end..]),
        original,
        "only the stop's numbers change"
    );
    assert_eq!(view(&url)["undo"], 1, "one pick, one step");
    assert_eq!(
        browser.eval("document.getElementById('stop-colour_map.points').value"),
        json!("#336699")
    );
    close(browser, studio);
}

/// A distortion term switched off: `enabled: false` is written into the
/// term, the image changes to the in-process render of the new text, and a
/// second tab shows the switch off and the new text.
#[test]
fn a_distortion_term_disabled_changes_the_text_and_the_image() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let (dir, _, original, studio, url, mut browser) = opened(
        &chromium,
        "studio-term-off",
        "scenes/gilet/multi_blend_bumps.ron",
    );
    let before = browser.canvas();
    assert_eq!(
        browser.eval("document.getElementById('operator-distortion.terms[4]').value"),
        json!("Blend")
    );
    // A second tab follows.
    let port = url.rsplit(':').next().unwrap().parse().unwrap();
    let mut other = open_page(&chromium, &dir.join("b"), port);
    let generation = browser.eval("studio.generation");
    browser.eval(
        "(() => { const c = document.getElementById('enabled-distortion.terms[4]'); \
         c.click(); })()",
    );
    let off = "operator: Blend, enabled: false),";
    until(60, "the switch reaches the text", || {
        text(&url).contains(off)
    });
    assert_eq!(text(&url), original.replacen("operator: Blend),", off, 1));
    rested(&mut browser, &generation);
    changed_as_the_cli_renders(&mut browser, &before, &dir, &url);
    assert_eq!(
        browser.eval("document.getElementById('enabled-distortion.terms[4]').checked"),
        json!(false)
    );
    other.wait_until(
        "!document.getElementById('enabled-distortion.terms[4]').checked && \
         document.getElementById('text').value.includes('operator: Blend, enabled: false),')",
        60,
    );
    drop(other);
    close(browser, studio);
}

/// Gilet & Dischler's 2D shape transfer function painted with the brush:
/// the cell under the pointer takes the brush's value in the text.
#[test]
fn a_transfer_grid_is_painted_with_the_brush() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let (_dir, _, original, studio, url, mut browser) =
        opened(&chromium, "studio-grid", "scenes/gilet/mushrooms.ron");
    let id = "grid-distortion.terms[0].transfer.Grid.rows";
    let at = browser.eval(&format!(
        "(() => {{ const c = document.getElementById({}); c.scrollIntoView(); \
         const r = c.getBoundingClientRect(); \
         return [r.left + r.width * 0.5 / 9, r.top + r.height * 0.5 / 9]; }})()",
        serde_json::to_string(id).unwrap()
    ));
    let (x, y) = (at[0].as_f64().unwrap(), at[1].as_f64().unwrap());
    let generation = browser.eval("studio.generation");
    for (kind, buttons) in [("mousePressed", 1), ("mouseReleased", 0)] {
        browser.call(
            "Input.dispatchMouseEvent",
            json!({ "type": kind, "x": x, "y": y, "button": "left", "buttons": buttons, "clickCount": 1 }),
        );
    }
    let first_row = "[1.0, 0.0, 0.0, 0.0, 0.3, 1.0, 1.0, 1.0, 1.0],";
    until(60, "the painted cell reaches the text", || {
        text(&url).contains(first_row)
    });
    assert_eq!(
        text(&url),
        original.replacen(
            "[0.0, 0.0, 0.0, 0.0, 0.3, 1.0, 1.0, 1.0, 1.0],",
            first_row,
            1
        )
    );
    rested(&mut browser, &generation);
    assert_eq!(view(&url)["grids"][0]["values"][0], 1.0);
    close(browser, studio);
}

/// A distortion's vector field switched in its menu: the field is written
/// into the text, and the image changes to the in-process render of the new
/// text.
#[test]
fn a_vector_field_switched_changes_the_text_and_the_image() {
    let Some(chromium) = chromium_or_skip() else {
        return;
    };
    let (dir, _, original, studio, url, mut browser) =
        opened(&chromium, "studio-field", "scenes/gilet/field_boundary.ron");
    assert!(original.contains("field: Boundary,"), "{original}");
    let before = browser.canvas();
    assert_eq!(
        browser.eval("document.getElementById('field-distortion').value"),
        json!("Boundary")
    );
    let generation = browser.eval("studio.generation");
    browser.eval(
        "(() => { const f = document.getElementById('field-distortion'); \
         f.value = 'Curl'; f.dispatchEvent(new Event('change')); })()",
    );
    until(60, "the field reaches the text", || {
        text(&url).contains("field: Curl(")
    });
    let edited_text = text(&url);
    assert!(!edited_text.contains("field: Boundary,"), "{edited_text}");
    rested(&mut browser, &generation);
    changed_as_the_cli_renders(&mut browser, &before, &dir, &url);
    close(browser, studio);
}
