//! Gmsh `.msh` parser + validation on arbitrary bytes: must return, never panic or abort.
#![no_main]

use std::path::Path;

use deform_mesh::MeshOptions;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("fuzz.msh");
    if let Ok(raw) = deform_mesh::io::parse_msh(data, path) {
        let _ = raw.into_mesh(path, &MeshOptions::default());
    }
});
