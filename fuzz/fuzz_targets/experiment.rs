//! Experiment RON (`Experiment::parse`: syntax, then every setting) on arbitrary bytes:
//! must return, never panic or abort.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = deform_learn::experiment::Experiment::parse(text, Path::new("fuzz.ron"));
    }
});
