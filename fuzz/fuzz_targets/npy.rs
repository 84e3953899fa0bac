//! `.npy` header and data (`npy::parse`) on arbitrary bytes: must return, never panic or
//! abort (hostile shapes included).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = deform_learn::npy::parse(data);
});
