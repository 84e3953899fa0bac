//! The contributor walkthroughs of `docs/architecture.md` stay true: each line starting with
//! "Checked:" names an enum, the file that defines it and the files that must name every one
//! of its variants (as `Enum::Variant` or, in RON text, `Variant(`). Adding a variant
//! without following the walkthrough, or moving a file it names, fails here.

use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The variants of `pub enum name` in `text` (lines at the enum's own indentation).
fn variants(text: &str, name: &str) -> Vec<String> {
    let start = text
        .find(&format!("pub enum {name} "))
        .unwrap_or_else(|| panic!("no `pub enum {name}`"));
    let body = &text[start..];
    let mut depth = 0i32;
    let mut out = Vec::new();
    for line in body.lines() {
        let trimmed = line.trim_start();
        let indent = line.len() - trimmed.len();
        if depth == 1 && indent == 4 && trimmed.starts_with(|c: char| c.is_ascii_uppercase()) {
            let end = trimmed
                .find(|c: char| !c.is_alphanumeric() && c != '_')
                .unwrap_or(trimmed.len());
            out.push(trimmed[..end].to_owned());
        }
        let code = line.split("//").next().unwrap_or("");
        depth += code.matches('{').count() as i32 - code.matches('}').count() as i32;
        if depth == 0 && !out.is_empty() {
            break;
        }
    }
    out
}

/// The backquoted words of a line.
fn quoted(line: &str) -> Vec<&str> {
    line.split('`').skip(1).step_by(2).collect()
}

#[test]
fn every_walkthrough_check_holds() {
    let doc = std::fs::read_to_string(root().join("docs/architecture.md")).unwrap();
    let checks: Vec<&str> = doc.lines().filter(|l| l.starts_with("Checked:")).collect();
    assert!(checks.len() >= 4, "the walkthroughs' checks are gone");
    let mut missing = Vec::new();
    for line in checks {
        let words = quoted(line);
        let (name, defined, named_in) = (words[0], words[1], &words[2..]);
        let text = std::fs::read_to_string(root().join(defined))
            .unwrap_or_else(|e| panic!("{defined}: {e}"));
        let all = variants(&text, name);
        assert!(!all.is_empty(), "{name} in {defined} has no variants");
        for file in named_in {
            let text = std::fs::read_to_string(root().join(file))
                .unwrap_or_else(|e| panic!("{file}: {e}"));
            for v in &all {
                let path = format!("{name}::{v}");
                let ron = format!("{v}(");
                let named = text.match_indices(&path).any(|(at, _)| {
                    !text[at + path.len()..].starts_with(|c: char| c.is_alphanumeric())
                });
                if !named && !text.contains(&ron) {
                    missing.push(format!("{file} does not name {name}::{v}"));
                }
            }
        }
    }
    assert!(
        missing.is_empty(),
        "walkthroughs not followed: {missing:#?}"
    );
}

#[test]
fn variants_are_read_at_the_enums_own_level() {
    let text = "/// doc\npub enum E {\n    /// A.\n    A { x: f64 },\n    B(Inner),\n    C,\n}\npub enum F {\n    D,\n}\n";
    assert_eq!(variants(text, "E"), ["A", "B", "C"]);
}
