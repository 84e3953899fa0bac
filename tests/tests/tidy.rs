//! Tidiness of the sources, checked as an ordinary test (as rust-analyzer keeps one): every
//! `.rs` file opens with a `//!` doc comment, the crates depend on each other exactly as
//! `docs/architecture.md` lists, no function outside tests is longer than
//! [`MAX_FUNCTION_LINES`], and the docs name no repository file that does not exist.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// "About 150 lines": a function body may run a few lines over.
const MAX_FUNCTION_LINES: usize = 160;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Every file under `dir` (relative to the root) whose name ends with `ext`.
fn files(dir: &str, ext: &str) -> Vec<PathBuf> {
    fn walk(dir: &Path, ext: &str, out: &mut Vec<PathBuf>) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for e in entries.flatten() {
            let p = e.path();
            let name = e.file_name().to_string_lossy().into_owned();
            if p.is_dir() {
                if name != "target" && !name.starts_with('.') {
                    walk(&p, ext, out);
                }
            } else if name.ends_with(ext) {
                out.push(p);
            }
        }
    }
    let mut out = Vec::new();
    walk(&root().join(dir), ext, &mut out);
    out.sort();
    out
}

fn sources() -> Vec<PathBuf> {
    ["crates", "xtask", "tests"]
        .iter()
        .flat_map(|d| files(d, ".rs"))
        .collect()
}

fn relative(p: &Path) -> String {
    p.strip_prefix(root())
        .unwrap_or(p)
        .to_string_lossy()
        .into_owned()
}

#[test]
fn every_source_file_opens_with_a_module_doc() {
    let missing: Vec<String> = sources()
        .iter()
        .filter(|p| {
            !std::fs::read_to_string(p)
                .unwrap()
                .trim_start()
                .starts_with("//!")
        })
        .map(|p| relative(p))
        .collect();
    assert!(missing.is_empty(), "no `//!` at the top of {missing:?}");
}

/// The deform crates a manifest depends on (normal dependencies only).
fn deform_dependencies(manifest: &Path) -> BTreeSet<String> {
    let text = std::fs::read_to_string(manifest).unwrap();
    let mut section = String::new();
    let mut deps = BTreeSet::new();
    for line in text.lines() {
        let line = line.trim();
        if line.starts_with('[') {
            section = line.to_owned();
        } else if section == "[dependencies]"
            && let Some(name) = line.split(['=', '.', ' ']).next()
            && name.starts_with("deform-")
        {
            deps.insert(name.to_owned());
        }
    }
    deps
}

#[test]
fn crate_dependencies_match_the_architecture_doc() {
    // The doc's edge list: lines `- crate -> dep, dep` under "Dependency edges".
    let doc = std::fs::read_to_string(root().join("docs/architecture.md")).unwrap();
    let edges = doc
        .split("Dependency edges")
        .nth(1)
        .expect("docs/architecture.md lists its dependency edges");
    let mut listed = BTreeSet::new();
    for line in edges.lines().skip(1) {
        let line = line.trim();
        if line.is_empty() && !listed.is_empty() {
            break;
        }
        let Some(rest) = line.strip_prefix("- `") else {
            continue;
        };
        let (from, to) = rest.split_once("` -> ").expect("`crate` -> deps");
        for dep in to.split(',').map(|d| d.trim().trim_matches('`')) {
            if dep != "none" {
                listed.insert((from.to_owned(), dep.to_owned()));
            }
        }
    }
    let mut actual = BTreeSet::new();
    for dir in [
        "crates/setters",
        "crates/fs",
        "crates/contact",
        "crates/mesh",
        "crates/materials",
        "crates/solvers",
        "crates/assembly",
    ]
    .into_iter()
    .chain([
        "crates/integrator",
        "crates/learn",
        "crates/studies",
        "crates/python",
        "crates/hack",
        "xtask",
        "tests",
    ]) {
        let manifest = root().join(dir).join("Cargo.toml");
        let text = std::fs::read_to_string(&manifest).unwrap();
        let name = text
            .lines()
            .find_map(|l| l.strip_prefix("name = \""))
            .and_then(|l| l.strip_suffix('"'))
            .unwrap()
            .to_owned();
        for dep in deform_dependencies(&manifest) {
            actual.insert((name.clone(), dep));
        }
    }
    let missing: Vec<_> = actual.difference(&listed).collect();
    let stale: Vec<_> = listed.difference(&actual).collect();
    assert!(
        missing.is_empty() && stale.is_empty(),
        "edges in Cargo.toml but not in the doc: {missing:?}; in the doc but not in Cargo.toml: {stale:?}"
    );
}

/// `(name, first line, length)` of every function in `text` outside `#[cfg(test)]` modules.
fn functions(text: &str) -> Vec<(String, usize, usize)> {
    let lines: Vec<&str> = text.lines().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i].trim_start();
        if line.starts_with("#[cfg(test)]") {
            break; // test modules sit at the end of a file by convention
        }
        let is_fn = line
            .split_whitespace()
            .find(|w| !["pub", "pub(crate)", "const", "unsafe", "async"].contains(w))
            == Some("fn");
        if !is_fn || line.starts_with("//") {
            i += 1;
            continue;
        }
        let name = line
            .split("fn ")
            .nth(1)
            .and_then(|s| s.split(['(', '<']).next())
            .unwrap_or("?")
            .to_owned();
        // From the line with the body's opening brace to the line that closes it.
        let (mut depth, mut opened, mut j) = (0i64, false, i);
        while j < lines.len() {
            for c in lines[j].chars() {
                match c {
                    '{' => {
                        depth += 1;
                        opened = true;
                    }
                    '}' => depth -= 1,
                    ';' if !opened && depth == 0 => break,
                    _ => {}
                }
            }
            if (opened && depth <= 0) || (!opened && lines[j].trim_end().ends_with(';')) {
                break;
            }
            j += 1;
        }
        out.push((name, i + 1, j + 1 - i));
        i = j + 1;
    }
    out
}

#[test]
fn no_function_outside_tests_is_longer_than_the_limit() {
    let mut long = Vec::new();
    for p in sources() {
        let rel = relative(&p);
        if rel.contains("/tests/") || rel.starts_with("tests/") || rel.contains("/benches/") {
            continue;
        }
        let text = std::fs::read_to_string(&p).unwrap();
        for (name, line, len) in functions(&text) {
            if len > MAX_FUNCTION_LINES {
                long.push(format!("{rel}:{line} {name} ({len} lines)"));
            }
        }
    }
    assert!(
        long.is_empty(),
        "functions over {MAX_FUNCTION_LINES} lines: {long:#?}"
    );
}

#[test]
fn the_line_counter_counts_a_function() {
    let text =
        "/// doc\npub fn f(\n    a: usize,\n) -> usize {\n    let b = { a };\n    b\n}\nfn g();\n";
    let f = functions(text);
    assert_eq!(f[0], ("f".to_owned(), 2, 6));
    assert_eq!(f[1], ("g".to_owned(), 8, 1));
}

/// Repository paths in backticks in a markdown text.
fn named_paths(text: &str) -> Vec<String> {
    const ROOTS: [&str; 8] = [
        "crates/", "xtask/", "tests/", "assets/", "docs/", "bench/", "scripts/", "fuzz/",
    ];
    text.split('`')
        .skip(1)
        .step_by(2)
        .filter(|s| ROOTS.iter().any(|r| s.starts_with(r)))
        .filter(|s| !s.contains(['*', '{', '<', ' ']))
        .map(|s| {
            s.split(':')
                .next()
                .unwrap_or(s)
                .trim_end_matches('/')
                .to_owned()
        })
        .collect()
}

#[test]
fn docs_name_no_missing_file() {
    let mut docs = files("docs", ".md");
    docs.push(root().join("README.md"));
    let mut missing = Vec::new();
    for doc in docs {
        let text = std::fs::read_to_string(&doc).unwrap();
        for path in named_paths(&text) {
            if !root().join(&path).exists() {
                missing.push(format!("{}: {path}", relative(&doc)));
            }
        }
    }
    assert!(missing.is_empty(), "docs name missing files: {missing:#?}");
}

#[test]
fn nothing_names_files_outside_the_repository() {
    let mut texts = files("docs", ".md");
    texts.push(root().join("README.md"));
    texts.extend(sources());
    texts.extend(files("assets", ".ron"));
    // Built from parts so that this file does not name the folder itself.
    let needle = ["shared", "/"].concat();
    let outside: Vec<String> = texts
        .iter()
        .filter(|p| std::fs::read_to_string(p).unwrap().contains(&needle))
        .map(|p| relative(p))
        .collect();
    assert!(
        outside.is_empty(),
        "name files outside the repository: {outside:?}"
    );
}

/// The longest a source file may be: what a reader holds in mind at once.
const MAX_FILE_LINES: usize = 1000;

#[test]
fn no_source_file_is_longer_than_the_limit() {
    let long: Vec<String> = sources()
        .iter()
        .filter_map(|p| {
            let lines = std::fs::read_to_string(p).unwrap().lines().count();
            (lines > MAX_FILE_LINES).then(|| format!("{}: {lines} lines", relative(p)))
        })
        .collect();
    assert!(
        long.is_empty(),
        "files over {MAX_FILE_LINES} lines: {long:#?}"
    );
}

/// A crate's modules: path segments (`["amg"]` for `amg/mod.rs` or `amg.rs`) to file.
fn modules(src: &Path) -> std::collections::BTreeMap<Vec<String>, PathBuf> {
    let mut out = std::collections::BTreeMap::new();
    for file in files(&relative(src), ".rs") {
        let rel = file.strip_prefix(src).unwrap().with_extension("");
        let mut parts: Vec<String> = rel.iter().map(|s| s.to_string_lossy().into()).collect();
        match parts.last().map(String::as_str) {
            Some("lib" | "main") => parts.clear(),
            Some("mod") => {
                parts.pop();
            }
            _ => {}
        }
        out.insert(parts, file);
    }
    out
}

/// The `crate::`, `super::` and `self::` paths of `text` (comments left out), each as its
/// root and segments; `use crate::{a::b, c}` groups give one path per item.
fn module_paths(text: &str) -> Vec<(String, Vec<String>)> {
    let code: String = text
        .lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect::<Vec<_>>()
        .join("\n");
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    let mut out = Vec::new();
    for root in ["crate", "super", "self"] {
        let pattern = format!("{root}::");
        for (at, _) in code.match_indices(&pattern) {
            if code[..at].chars().next_back().is_some_and(ident) {
                continue;
            }
            let rest = &code[at + pattern.len()..];
            if let Some(group) = rest.strip_prefix('{') {
                let group = &group[..group.find('}').unwrap_or(group.len())];
                for item in group.split(',') {
                    let item = item.split(" as ").next().unwrap().trim();
                    let segs: Vec<String> = item
                        .split("::")
                        .filter(|s| !s.is_empty() && *s != "*" && s.chars().all(ident))
                        .map(String::from)
                        .collect();
                    out.push((root.to_owned(), segs));
                }
            } else {
                let end = rest
                    .find(|c: char| !ident(c) && c != ':')
                    .unwrap_or(rest.len());
                let segs = rest[..end].split("::").filter(|s| !s.is_empty());
                out.push((root.to_owned(), segs.map(String::from).collect()));
            }
        }
    }
    out
}

/// Which module files each module file of `src` imports (its own children and the
/// modules above it, whose re-exports these are, left out).
fn module_edges(src: &Path) -> Vec<(PathBuf, BTreeSet<PathBuf>)> {
    let modules = modules(src);
    let mut edges = Vec::new();
    for (m, file) in &modules {
        let text = std::fs::read_to_string(file).unwrap();
        let mut targets = BTreeSet::new();
        for (root, mut segs) in module_paths(&text) {
            let mut base: Vec<String> = match root.as_str() {
                "crate" => Vec::new(),
                "super" => m[..m.len().saturating_sub(1)].to_vec(),
                _ => m.clone(),
            };
            while segs.first().is_some_and(|s| s == "super") {
                base.pop();
                segs.remove(0);
            }
            let target = (0..=segs.len()).rev().find_map(|k| {
                let key: Vec<String> = base.iter().chain(&segs[..k]).cloned().collect();
                modules.contains_key(&key).then_some(key)
            });
            let Some(t) = target else { continue };
            let above = t.len() <= m.len() && m[..t.len()] == t[..];
            let child = t.len() > m.len() && t[..m.len()] == m[..];
            if !(above || child) {
                targets.insert(modules[&t].clone());
            }
        }
        edges.push((file.clone(), targets));
    }
    edges
}

/// Files that import each other, directly or round a longer circle (Tarjan's strongly
/// connected components of more than one file).
fn circles(edges: &[(PathBuf, BTreeSet<PathBuf>)]) -> Vec<Vec<String>> {
    let index_of = |p: &PathBuf| edges.iter().position(|(f, _)| f == p);
    let graph: Vec<Vec<usize>> = edges
        .iter()
        .map(|(_, t)| t.iter().filter_map(index_of).collect())
        .collect();
    // Reachability by repeated search: the graphs are a few dozen files.
    let reach = |from: usize| {
        let (mut seen, mut stack) = (vec![false; graph.len()], vec![from]);
        while let Some(v) = stack.pop() {
            for &w in &graph[v] {
                if !seen[w] {
                    seen[w] = true;
                    stack.push(w);
                }
            }
        }
        seen
    };
    let reached: Vec<Vec<bool>> = (0..graph.len()).map(reach).collect();
    let mut done = vec![false; graph.len()];
    let mut out = Vec::new();
    for v in 0..graph.len() {
        if done[v] || !reached[v][v] {
            continue;
        }
        let comp: Vec<usize> = (0..graph.len())
            .filter(|&w| reached[v][w] && reached[w][v])
            .collect();
        comp.iter().for_each(|&w| done[w] = true);
        out.push(comp.iter().map(|&w| relative(&edges[w].0)).collect());
    }
    out
}

#[test]
fn no_two_source_files_import_each_other() {
    let mut found = Vec::new();
    for dir in files("crates", "Cargo.toml")
        .iter()
        .chain(&files("xtask", "Cargo.toml"))
    {
        let src = dir.parent().unwrap().join("src");
        if src.is_dir() {
            found.extend(circles(&module_edges(&src)));
        }
    }
    assert!(found.is_empty(), "circles between files: {found:#?}");
}

#[test]
fn the_circle_check_finds_a_circle() {
    let (a, b, c) = (
        PathBuf::from("a.rs"),
        PathBuf::from("b.rs"),
        PathBuf::from("c.rs"),
    );
    let edges = vec![
        (a.clone(), BTreeSet::from([b.clone()])),
        (b.clone(), BTreeSet::from([a.clone(), c.clone()])),
        (c.clone(), BTreeSet::new()),
    ];
    assert_eq!(
        circles(&edges),
        vec![vec!["a.rs".to_owned(), "b.rs".to_owned()]]
    );
    let paths = module_paths("use crate::{a::B, c};\nlet x = super::d::e(); // crate::f\n");
    let names: Vec<String> = paths
        .iter()
        .map(|(r, s)| format!("{r}:{}", s.join("/")))
        .collect();
    assert_eq!(names, ["crate:a/B", "crate:c", "super:d/e"]);
}

/// The features `cargo tree` resolves for each package of a build (`args` select it): package
/// name and version to the feature lists of its instances (proc-macro and build-script
/// instances resolve apart).
fn resolved_features(args: &[&str]) -> std::collections::BTreeMap<String, BTreeSet<String>> {
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let out = std::process::Command::new(cargo)
        .current_dir(root())
        .args(["tree", "--offline", "--prefix", "none", "-f", "{p}|{f}"])
        .args(args)
        .output()
        .expect("cargo tree runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut found = std::collections::BTreeMap::<String, BTreeSet<String>>::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let Some((package, features)) = line.split_once('|') else {
            continue;
        };
        let name: Vec<&str> = package.split_whitespace().take(2).collect();
        let features = features.split_whitespace().next().unwrap_or("");
        found
            .entry(name.join(" "))
            .or_default()
            .insert(features.to_owned());
    }
    found
}

/// The runner, the Python module and the test build resolve every dependency they share with
/// the same features (`crates/hack` pins them), so each is built once for all three: when
/// the sets differed, `pip install` after the demo rebuilt every crate (issue 57). PyO3's
/// crates belong to the module alone; the extension-module feature is maturin's.
#[test]
fn the_runner_the_module_and_the_tests_share_one_build_of_each_dependency() {
    let module = resolved_features(&[
        "-p",
        "deform-python",
        "--features",
        "pyo3/extension-module",
        "-e",
        "normal,build",
    ]);
    let runner = resolved_features(&["-p", "xtask", "-e", "normal,build"]);
    let tests = resolved_features(&["--workspace", "-e", "normal,build,dev"]);
    let mut differ = Vec::new();
    for (other, what) in [(&runner, "the runner"), (&tests, "the test build")] {
        for (package, features) in &module {
            let ours = package.starts_with("pyo3") || package.starts_with("deform-python");
            // An instance only one side builds (a proc-macro's copy without features) is no
            // rebuild; a feature list both have but with other members is.
            if let Some(theirs) = other.get(package)
                && !ours
                && !features.iter().all(|f| f.is_empty() || theirs.contains(f))
            {
                differ.push(format!(
                    "{package}: the module {features:?}, {what} {theirs:?}"
                ));
            }
        }
    }
    assert!(
        differ.is_empty(),
        "add the missing features to crates/hack/Cargo.toml:\n{}",
        differ.join("\n")
    );
}
