//! TetGen `.node` + `.ele` parser + validation on arbitrary bytes (split at the first NUL).
#![no_main]

use std::path::Path;

use deform_mesh::MeshOptions;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let split = data.iter().position(|&b| b == 0).unwrap_or(data.len());
    let (node, ele) = (&data[..split], data.get(split + 1..).unwrap_or(&[]));
    let (np, ep) = (Path::new("f.node"), Path::new("f.ele"));
    if let Ok(raw) = deform_mesh::io::parse_tetgen(node, ele, np, ep) {
        let _ = raw.into_mesh(ep, &MeshOptions::default());
    }
});
