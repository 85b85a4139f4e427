//! The source layout: no import circle between the files of a crate.
//!
//! Every `crate::`, `super::` and `self::` path in a crate's `src/` (in `use`
//! statements and inline in code) is resolved to the file that defines it; re-exports
//! of a crate root or a `mod.rs` are followed to their source, so a facade is not a
//! dependency. The test fails on any strongly connected set of two or more files and
//! names the edges inside it. `cargo test -p nimbus-tests --test layout -- --nocapture`
//! also prints each file's dependencies (the module map of ARCHITECTURE.md).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const CRATES: [&str; 4] = ["engine", "modeler", "models", "app"];

/// One crate's modules: module path (e.g. ["integrator", "bdpt"]) -> file.
struct Crate {
    files: BTreeMap<Vec<String>, PathBuf>,
    /// Per facade module (crate root or mod.rs): item name -> the path it re-exports.
    reexports: BTreeMap<Vec<String>, BTreeMap<String, Vec<String>>>,
}

fn module_path(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).unwrap();
    let mut parts: Vec<String> = rel.iter().map(|s| s.to_string_lossy().into_owned()).collect();
    let last = parts.pop().unwrap();
    let stem = last.trim_end_matches(".rs");
    if stem != "mod" && stem != "lib" && stem != "main" {
        parts.push(stem.to_string());
    }
    parts
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The text with comments, string and char literals blanked (kept as spaces, so line
/// structure and brace depth are those of the code).
fn strip(text: &str) -> String {
    let b: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        if c == '/' && b.get(i + 1) == Some(&'/') {
            while i < b.len() && b[i] != '\n' {
                i += 1;
            }
        } else if c == '/' && b.get(i + 1) == Some(&'*') {
            let mut depth = 0;
            while i < b.len() {
                if b[i] == '/' && b.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                } else if b[i] == '*' && b.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    if b[i] == '\n' {
                        out.push('\n');
                    }
                    i += 1;
                }
            }
        } else if c == 'r'
            && (b.get(i + 1) == Some(&'"') || b.get(i + 1) == Some(&'#'))
            && !ident_char(b.get(i.wrapping_sub(1)))
        {
            // raw string r"..." or r#"..."#
            let mut j = i + 1;
            let mut hashes = 0;
            while b.get(j) == Some(&'#') {
                hashes += 1;
                j += 1;
            }
            if b.get(j) != Some(&'"') {
                out.push(c);
                i += 1;
                continue;
            }
            j += 1;
            loop {
                if j >= b.len() {
                    break;
                }
                if b[j] == '"' && (0..hashes).all(|h| b.get(j + 1 + h) == Some(&'#')) {
                    j += 1 + hashes;
                    break;
                }
                if b[j] == '\n' {
                    out.push('\n');
                }
                j += 1;
            }
            out.push(' ');
            i = j;
        } else if c == '"' {
            i += 1;
            while i < b.len() && b[i] != '"' {
                if b[i] == '\\' {
                    i += 1;
                } else if b[i] == '\n' {
                    out.push('\n');
                }
                i += 1;
            }
            i += 1;
            out.push(' ');
        } else if c == '\'' {
            // a char literal ('x', '\n', '\u{..}') or a lifetime ('a)
            let close = if b.get(i + 1) == Some(&'\\') {
                (i + 2..b.len().min(i + 12)).find(|&j| b[j] == '\'')
            } else if b.get(i + 2) == Some(&'\'') {
                Some(i + 2)
            } else {
                None
            };
            match close {
                Some(j) => {
                    out.push(' ');
                    i = j + 1;
                }
                None => {
                    out.push(c);
                    i += 1;
                }
            }
        } else {
            out.push(c);
            i += 1;
        }
    }
    out
}

fn ident_char(c: Option<&char>) -> bool {
    c.is_some_and(|c| c.is_alphanumeric() || *c == '_')
}

/// Expands a use tree (`a::{b, c::{d, e as f}}`) into its paths.
fn expand_use(tree: &str) -> Vec<Vec<String>> {
    fn go(s: &str, prefix: &[String], out: &mut Vec<Vec<String>>) {
        let s = s.trim();
        if s.is_empty() {
            return;
        }
        if let Some(open) = s.find('{') {
            let head: Vec<String> =
                s[..open].split("::").map(str::trim).filter(|x| !x.is_empty()).map(String::from).collect();
            let inner = &s[open + 1..s.rfind('}').unwrap_or(s.len())];
            let mut p = prefix.to_vec();
            p.extend(head);
            let mut depth = 0;
            let mut start = 0;
            for (i, c) in inner.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        go(&inner[start..i], &p, out);
                        start = i + 1;
                    }
                    _ => {}
                }
            }
            go(&inner[start..], &p, out);
        } else {
            let s = s.split(" as ").next().unwrap().trim();
            let mut p = prefix.to_vec();
            p.extend(s.split("::").map(str::trim).filter(|x| !x.is_empty()).map(String::from));
            out.push(p);
        }
    }
    let mut out = Vec::new();
    go(tree, &[], &mut out);
    out
}

/// A reference found in a file: the path as written, and whether it sits inside an
/// inline module (where `super` is the file's own module).
struct Reference {
    path: Vec<String>,
    inline_depth: usize,
}

struct Scan {
    refs: Vec<Reference>,
    /// `pub use` paths at the file's top level: (item name, path).
    reexports: Vec<(String, Vec<String>)>,
}

fn scan(code: &str) -> Scan {
    let mut refs = Vec::new();
    let mut reexports = Vec::new();
    // Brace depths at which inline `mod name {` blocks opened.
    let mut inline: Vec<i32> = Vec::new();
    let mut depth = 0i32;
    let chars: Vec<char> = code.chars().collect();
    let mut i = 0;
    let word_at = |i: usize| -> Option<String> {
        if ident_char(chars.get(i.wrapping_sub(1))) || !ident_char(chars.get(i)) {
            return None;
        }
        let mut j = i;
        while ident_char(chars.get(j)) {
            j += 1;
        }
        Some(chars[i..j].iter().collect())
    };
    while i < chars.len() {
        let c = chars[i];
        if c == '{' {
            depth += 1;
            i += 1;
            continue;
        }
        if c == '}' {
            depth -= 1;
            if inline.last() == Some(&depth) {
                inline.pop();
            }
            i += 1;
            continue;
        }
        let Some(w) = word_at(i) else {
            i += 1;
            continue;
        };
        let end = i + w.chars().count();
        if w == "mod" {
            // `mod name {`: an inline module opens at the next brace.
            let rest: String = chars[end..chars.len().min(end + 80)].iter().collect();
            let rest = rest.trim_start();
            let name_len = rest.chars().take_while(|c| c.is_alphanumeric() || *c == '_').count();
            if rest[name_len..].trim_start().starts_with('{') {
                inline.push(depth);
            }
            i = end;
            continue;
        }
        if w == "use" {
            let stmt_end = (end..chars.len()).find(|&j| chars[j] == ';').unwrap_or(chars.len());
            let tree: String = chars[end..stmt_end].iter().collect();
            let before: String = chars[i.saturating_sub(12)..i].iter().collect();
            let is_pub = before.trim_end().ends_with("pub") || before.trim_end().ends_with("pub(crate)");
            for p in expand_use(&tree) {
                if is_pub && inline.is_empty() && depth == 0 {
                    let name = p.last().cloned().unwrap_or_default();
                    let alias = tree
                        .split(',')
                        .find_map(|part| {
                            let part = part.trim().trim_end_matches('}');
                            part.contains(&format!("{name} as "))
                                .then(|| part.rsplit(" as ").next().unwrap().trim().to_string())
                        })
                        .unwrap_or(name);
                    reexports.push((alias, p.clone()));
                }
                refs.push(Reference { path: p, inline_depth: inline.len() });
            }
            i = stmt_end;
            continue;
        }
        if chars.get(end) == Some(&':') && chars.get(end + 1) == Some(&':') {
            let mut path = vec![w.clone()];
            let mut j = end;
            while chars.get(j) == Some(&':') && chars.get(j + 1) == Some(&':') {
                j += 2;
                match word_at(j) {
                    Some(seg) => {
                        j += seg.chars().count();
                        path.push(seg);
                    }
                    None => break,
                }
            }
            refs.push(Reference { path, inline_depth: inline.len() });
            i = j;
            continue;
        }
        i = end;
    }
    Scan { refs, reexports }
}

/// The absolute module path a written path names, or None for external crates.
fn absolute(path: &[String], here: &[String], inline_depth: usize) -> Option<Vec<String>> {
    let mut out: Vec<String>;
    let mut rest = path;
    match path.first().map(String::as_str) {
        Some("crate") => {
            out = Vec::new();
            rest = &path[1..];
        }
        Some("self") => {
            out = here.to_vec();
            rest = &path[1..];
        }
        Some("super") => {
            out = here.to_vec();
            let mut inline = inline_depth;
            while rest.first().map(String::as_str) == Some("super") {
                if inline > 0 {
                    inline -= 1;
                } else {
                    out.pop()?;
                }
                rest = &rest[1..];
            }
        }
        _ => return None,
    }
    out.extend(rest.iter().filter(|s| *s != "self").cloned());
    Some(out)
}

fn load(name: &str) -> (Crate, BTreeMap<Vec<String>, Scan>) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
    let src = root.join(name).join("src");
    let mut paths = Vec::new();
    rust_files(&src, &mut paths);
    let mut files = BTreeMap::new();
    let mut scans = BTreeMap::new();
    let mut reexports = BTreeMap::new();
    for p in paths {
        if p.file_name().unwrap() == "main.rs" && p.parent().unwrap() == src {
            continue; // the binary is its own crate
        }
        let m = module_path(&src, &p);
        let s = scan(&strip(&std::fs::read_to_string(&p).unwrap()));
        let is_facade = p.file_name().is_some_and(|f| f == "mod.rs" || f == "lib.rs");
        if is_facade {
            let mut map = BTreeMap::new();
            for (item, target) in &s.reexports {
                if let Some(abs) = absolute(target, &m, 0).or_else(|| {
                    // `pub use child::Item` written relative to the facade
                    let mut a = m.clone();
                    a.extend(target.iter().cloned());
                    Some(a)
                }) {
                    map.insert(item.clone(), abs);
                }
            }
            reexports.insert(m.clone(), map);
        }
        files.insert(m.clone(), p);
        scans.insert(m, s);
    }
    (Crate { files, reexports }, scans)
}

impl Crate {
    /// The file that defines what `abs` names: the longest module prefix, with facade
    /// re-exports followed (at most a few hops).
    fn resolve(&self, abs: &[String]) -> Option<Vec<String>> {
        let mut abs = abs.to_vec();
        for _ in 0..8 {
            let n = (0..=abs.len()).rev().find(|&n| self.files.contains_key(&abs[..n]))?;
            let module = abs[..n].to_vec();
            let Some(next) = abs.get(n) else { return Some(module) };
            match self.reexports.get(&module).and_then(|r| r.get(next)) {
                Some(target) if target.as_slice() != abs.as_slice() => {
                    let mut t = target.clone();
                    t.extend(abs[n + 1..].iter().cloned());
                    abs = t;
                }
                _ => return Some(module),
            }
        }
        None
    }
}

fn name(m: &[String]) -> String {
    if m.is_empty() { "(root)".into() } else { m.join("::") }
}

/// Strongly connected components of two or more nodes (Tarjan).
fn cycles(graph: &BTreeMap<Vec<String>, BTreeSet<Vec<String>>>) -> Vec<Vec<Vec<String>>> {
    struct T<'a> {
        g: &'a BTreeMap<Vec<String>, BTreeSet<Vec<String>>>,
        index: BTreeMap<Vec<String>, usize>,
        low: BTreeMap<Vec<String>, usize>,
        stack: Vec<Vec<String>>,
        on: BTreeSet<Vec<String>>,
        out: Vec<Vec<Vec<String>>>,
    }
    fn visit(t: &mut T, v: &Vec<String>) {
        let i = t.index.len();
        t.index.insert(v.clone(), i);
        t.low.insert(v.clone(), i);
        t.stack.push(v.clone());
        t.on.insert(v.clone());
        for w in t.g.get(v).into_iter().flatten() {
            if !t.index.contains_key(w) {
                visit(t, w);
                let lw = t.low[w];
                let lv = t.low.get_mut(v).unwrap();
                *lv = (*lv).min(lw);
            } else if t.on.contains(w) {
                let iw = t.index[w];
                let lv = t.low.get_mut(v).unwrap();
                *lv = (*lv).min(iw);
            }
        }
        if t.low[v] == t.index[v] {
            let mut comp = Vec::new();
            loop {
                let w = t.stack.pop().unwrap();
                t.on.remove(&w);
                let done = &w == v;
                comp.push(w);
                if done {
                    break;
                }
            }
            if comp.len() > 1 {
                comp.sort();
                t.out.push(comp);
            }
        }
    }
    let mut t = T {
        g: graph,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on: BTreeSet::new(),
        out: Vec::new(),
    };
    for v in graph.keys() {
        if !t.index.contains_key(v) {
            visit(&mut t, v);
        }
    }
    t.out
}

/// File-level dependency graph of one crate: module -> modules it uses.
fn graph(name_: &str) -> BTreeMap<Vec<String>, BTreeSet<Vec<String>>> {
    let (krate, scans) = load(name_);
    let mut g: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = BTreeMap::new();
    for (m, s) in &scans {
        let facade = krate.reexports.contains_key(m);
        let entry = g.entry(m.clone()).or_default();
        for r in &s.refs {
            // `crate::`, `super::`, `self::`, or a path starting at a child module.
            let abs = absolute(&r.path, m, r.inline_depth).or_else(|| {
                let mut child = m.clone();
                child.push(r.path.first()?.clone());
                krate.files.contains_key(&child).then(|| {
                    let mut a = m.clone();
                    a.extend(r.path.iter().cloned());
                    a
                })
            });
            let Some(abs) = abs else { continue };
            // A facade's own re-exports are not dependencies.
            if facade && s.reexports.iter().any(|(_, p)| p == &r.path) {
                continue;
            }
            if let Some(target) = krate.resolve(&abs) {
                if &target != m {
                    entry.insert(target);
                }
            }
        }
    }
    g
}

#[test]
fn no_import_circle_between_files() {
    let mut failures = Vec::new();
    for c in CRATES {
        let g = graph(c);
        println!("{c}:");
        for (m, deps) in &g {
            let deps: Vec<String> = deps.iter().map(|d| name(d)).collect();
            println!("  {} -> {}", name(m), if deps.is_empty() { "-".into() } else { deps.join(", ") });
        }
        for comp in cycles(&g) {
            let set: BTreeSet<_> = comp.iter().cloned().collect();
            let edges: Vec<String> = comp
                .iter()
                .flat_map(|a| {
                    g[a].iter().filter(|b| set.contains(*b)).map(move |b| format!("{} -> {}", name(a), name(b)))
                })
                .collect();
            failures.push(format!(
                "{c}: circle between {}: {}",
                comp.iter().map(|m| name(m)).collect::<Vec<_>>().join(", "),
                edges.join("; ")
            ));
        }
    }
    assert!(failures.is_empty(), "import circles:\n{}", failures.join("\n"));
}

/// The checker itself: a circle written in a scratch crate is found, a facade's
/// re-exports and a test module's `use super::*` are not dependencies.
#[test]
fn the_checker_finds_a_circle() {
    let code = strip(
        "use crate::b::X; // crate::c::Y in a comment\nfn f() { let s = \"crate::c::Z\"; crate::d::g(); }\n\
         #[cfg(test)] mod tests { use super::*; use super::super::e::Q; }",
    );
    let s = scan(&code);
    let paths: Vec<String> = s.refs.iter().map(|r| r.path.join("::")).collect();
    assert_eq!(paths, ["crate::b::X", "crate::d::g", "super::*", "super::super::e::Q"]);
    let s2 = scan(&strip("fn g() { worker::spawn(); glam::Vec3::ZERO; }"));
    let paths2: Vec<String> = s2.refs.iter().map(|r| r.path.join("::")).collect();
    assert_eq!(paths2, ["worker::spawn", "glam::Vec3::ZERO"]);
    let here = vec!["a".to_string()];
    assert_eq!(absolute(&s.refs[2].path, &here, s.refs[2].inline_depth), Some(vec!["a".into(), "*".into()]));
    assert_eq!(absolute(&s.refs[3].path, &here, s.refs[3].inline_depth), Some(vec!["e".into(), "Q".into()]));
    assert_eq!(
        expand_use("crate::a::{B, c::{D, E as F}, self}"),
        vec![
            vec!["crate", "a", "B"],
            vec!["crate", "a", "c", "D"],
            vec!["crate", "a", "c", "E"],
            vec!["crate", "a", "self"]
        ]
        .into_iter()
        .map(|v| v.into_iter().map(String::from).collect::<Vec<_>>())
        .collect::<Vec<_>>()
    );
    let m = |s: &str| s.split("::").map(String::from).collect::<Vec<_>>();
    let mut g = BTreeMap::new();
    g.insert(m("a"), [m("b")].into_iter().collect::<BTreeSet<_>>());
    g.insert(m("b"), [m("c")].into_iter().collect());
    g.insert(m("c"), [m("a"), m("d")].into_iter().collect());
    g.insert(m("d"), BTreeSet::new());
    assert_eq!(cycles(&g), vec![vec![m("a"), m("b"), m("c")]]);
    g.get_mut(&m("c")).unwrap().remove(&m("a"));
    assert!(cycles(&g).is_empty());
}
