//! Every code block of README.md and docs/guide/ runs, so a doc cannot drift from the code
//! (issue 57). Each page runs in a folder of its own holding a link to the repository's
//! `assets/`: its RON blocks are the files they name on their first line (`// file:
//! NAME.ron`), written in page order, and its shell blocks run there in order, with `cargo
//! xtask` the runner built for this test. Rust blocks are doc tests of `deform-tests`
//! (`tests/src/lib.rs` includes every page) and Python blocks run under pytest
//! (`python/tests/test_guide.py`) in the same way; this test checks that both include every
//! page. Each block run is printed (`--nocapture`), and so is each block not run here, with
//! who runs it.

use std::path::{Path, PathBuf};
use std::process::Command;

/// A fenced code block: its info string, first line (1-based) and text.
struct Block {
    info: String,
    line: usize,
    text: String,
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// README.md, then the guide's pages in name order.
fn pages() -> Vec<PathBuf> {
    let mut guide: Vec<PathBuf> = std::fs::read_dir(root().join("docs/guide"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    guide.sort();
    std::iter::once(root().join("README.md"))
        .chain(guide)
        .collect()
}

fn blocks(text: &str) -> Vec<Block> {
    let mut out = Vec::new();
    let mut open: Option<Block> = None;
    for (k, line) in text.lines().enumerate() {
        let fence = line.trim_start().strip_prefix("```");
        match (&mut open, fence) {
            (None, Some(info)) => {
                open = Some(Block {
                    info: info.trim().to_owned(),
                    line: k + 2,
                    text: String::new(),
                })
            }
            (Some(_), Some(_)) => out.push(open.take().unwrap()),
            (Some(b), None) => {
                b.text.push_str(line);
                b.text.push('\n');
            }
            (None, None) => {}
        }
    }
    assert!(open.is_none(), "a code block is never closed");
    out
}

/// The README's set-up commands are what CI itself runs (`.ci/run`), and building the Python
/// module is pytest's part: blocks whose first word is one of these are not run here.
const RUN_ELSEWHERE: [(&str, &str); 2] = [
    (
        "cargo xtask demo",
        "the demo: minutes; `cargo xtask demo` is its own command",
    ),
    (
        "pip install",
        "the Python install: `cargo xtask test` builds the module",
    ),
];

/// The shell block `text` run with bash in `dir`, `cargo xtask` being this build's runner.
fn run_shell(text: &str, dir: &Path, what: &str) {
    let script = format!(
        "set -euo pipefail\ncargo() {{ if [ \"$1\" = xtask ]; then shift; \"$XTASK\" \"$@\"; else command cargo \"$@\"; fi; }}\n{text}"
    );
    let out = Command::new("bash")
        .current_dir(dir)
        .env("XTASK", env!("CARGO_BIN_EXE_xtask"))
        .args(["-c", &script])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{what} failed:\n{text}\nstdout:\n{}\nstderr:\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn every_code_block_of_the_readme_and_the_guide_runs() {
    let includes = std::fs::read_to_string(root().join("tests/src/lib.rs")).unwrap();
    let pytest = std::fs::read_to_string(root().join("python/tests/test_guide.py")).unwrap();
    for page in pages() {
        let name = page.strip_prefix(root()).unwrap().display().to_string();
        let text = std::fs::read_to_string(&page).unwrap();
        let dir = tempfile::tempdir().unwrap();
        std::os::unix::fs::symlink(root().join("assets"), dir.path().join("assets")).unwrap();
        for b in blocks(&text) {
            let what = format!("{name}:{} ({})", b.line, b.info);
            let lang = b.info.split_whitespace().next().unwrap_or("");
            match lang {
                "ron" => {
                    let first = b.text.lines().next().unwrap_or("");
                    let file = first.strip_prefix("// file: ").unwrap_or_else(|| {
                        panic!("{what}: a RON block names its file on its first line (`// file: NAME.ron`)")
                    });
                    std::fs::write(dir.path().join(file.trim()), &b.text).unwrap();
                    println!("{what}: wrote {}", file.trim());
                }
                "sh" => {
                    let first = b.text.lines().find(|l| !l.trim().is_empty()).unwrap_or("");
                    if let Some((_, who)) = RUN_ELSEWHERE.iter().find(|(c, _)| first.starts_with(c))
                    {
                        println!("{what}: not run here: {who}");
                        continue;
                    }
                    run_shell(&b.text, dir.path(), &what);
                    println!("{what}: ran");
                }
                "rust" => {
                    let included = includes.contains(&format!("\"../../{name}\""));
                    assert!(
                        included,
                        "{what}: tests/src/lib.rs does not include {name}, so its Rust blocks are not run"
                    );
                    println!("{what}: a doc test of deform-tests");
                }
                "python" => {
                    let runs = pytest.contains("docs/guide") && pytest.contains("README.md");
                    assert!(runs, "{what}: python/tests/test_guide.py does not run it");
                    println!("{what}: run by python/tests/test_guide.py");
                }
                "text" | "" => println!("{what}: output, not code"),
                other => panic!("{what}: a block of `{other}`: say how it runs, or mark it `text`"),
            }
        }
    }
}
