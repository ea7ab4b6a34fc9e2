//! Any bytes as (scene functions, expression): parsing, checking and compiling
//! must never panic or hang, and whatever compiles must evaluate without panicking.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let (functions, expression) = text.split_once('\u{0}').unwrap_or(("", &text));
    hypertexture::pse::fuzz::compile_and_run(functions, expression);
});
