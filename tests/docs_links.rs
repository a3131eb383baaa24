//! The documents point at things that exist. README.md and every page of `docs/` (the
//! research log aside: it is history, and names what was there at the time) are read,
//! fenced code blocks left out, and:
//! - every relative Markdown link (`[text](target)`, images too) must resolve from the
//!   page's folder, and a `#anchor` into a Markdown page must be one of its headings;
//! - every repository path in backticks must exist: a token without spaces, `<`, `*` or
//!   `{` that contains a `/` and starts with one of `PREFIXES` or ends in one of
//!   `EXTENSIONS`, once a trailing `:line`, `#anchor` and punctuation are stripped.
//!   Paths a command writes at run time (`runs/...`, `policy.onnx`) start with none of
//!   the prefixes and are not required;
//! - in `docs/extending.md`, which tells a newcomer what to edit, every Rust name in
//!   backticks must be defined somewhere in `src/`: a call `name()` (or `Type::name()`,
//!   `module::name(args)`) as `fn name`, a CamelCase name as a `struct`, `enum`,
//!   `trait` or `type`, an ALL_CAPS name as a `const` or `static`, and in a path
//!   `a::b::C` every module as a `mod` and `Type::Variant` as written in the source; a
//!   snake_case name without parentheses (a function, field or config key) must at least
//!   occur as a word. A plain text search: it proves the name exists, not that it is the
//!   one meant.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

const PREFIXES: [&str; 10] = [
    "src/",
    "tests/",
    "benches/",
    "configs/",
    "experiments/",
    "policies/",
    "results/",
    "docs/",
    "mjcf/",
    "viz/",
];
const EXTENSIONS: [&str; 5] = [".rs", ".toml", ".md", ".py", ".sh"];

/// Pages whose Rust names are checked against the source.
const SYMBOL_PAGES: [&str; 1] = ["docs/extending.md"];

/// Path segments that name no module of this crate but are fine in a path.
const OUTER_MODULES: [&str; 5] = ["rall", "crate", "self", "super", "std"];

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// README.md and docs/*.md but the research log, as paths relative to the root.
fn documents() -> Vec<String> {
    let mut docs = vec!["README.md".to_string()];
    let mut pages: Vec<String> = std::fs::read_dir(root().join("docs"))
        .expect("docs/ exists")
        .map(|e| {
            e.expect("reading docs/")
                .file_name()
                .to_string_lossy()
                .into_owned()
        })
        .filter(|n| n.ends_with(".md") && n != "research-log.md")
        .map(|n| format!("docs/{n}"))
        .collect();
    pages.sort();
    docs.extend(pages);
    docs
}

/// `text` with the lines of fenced code blocks blanked (line numbers and byte offsets
/// of everything else unchanged).
fn prose(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut fenced = false;
    for line in text.split_inclusive('\n') {
        let fence = line.trim_start().starts_with("```");
        if fence || fenced {
            out.extend(line.chars().map(|c| if c == '\n' { '\n' } else { ' ' }));
        } else {
            out.push_str(line);
        }
        if fence {
            fenced = !fenced;
        }
    }
    out
}

/// Line number (from 1) of byte offset `at`.
fn line_of(text: &str, at: usize) -> usize {
    text[..at].matches('\n').count() + 1
}

/// Inline code spans: (byte range of the whole span, its content trimmed).
fn code_spans(text: &str) -> Vec<(std::ops::Range<usize>, String)> {
    let b = text.as_bytes();
    let run_at = |i: usize| b[i..].iter().take_while(|&&c| c == b'`').count();
    let mut spans = Vec::new();
    let mut i = 0;
    while i < b.len() {
        if b[i] != b'`' {
            i += 1;
            continue;
        }
        let n = run_at(i);
        let start = i;
        let mut j = i + n;
        let mut close = None;
        while j < b.len() {
            if b[j] == b'`' {
                let m = run_at(j);
                if m == n {
                    close = Some(j);
                    break;
                }
                j += m;
            } else {
                j += 1;
            }
        }
        match close {
            Some(c) => {
                let content = text[start + n..c].split_whitespace().collect::<Vec<_>>();
                spans.push((start..c + n, content.join(" ")));
                i = c + n;
            }
            // an unmatched run is literal text
            None => i = start + n,
        }
    }
    spans
}

/// Markdown link targets outside code spans: (byte offset, target).
fn links(text: &str, spans: &[(std::ops::Range<usize>, String)]) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    for (at, _) in text.match_indices("](") {
        if spans.iter().any(|(r, _)| r.contains(&at)) {
            continue;
        }
        let rest = &text[at + 2..];
        let mut depth = 1;
        let mut end = None;
        for (k, c) in rest.char_indices() {
            match c {
                '(' => depth += 1,
                ')' => {
                    depth -= 1;
                    if depth == 0 {
                        end = Some(k);
                        break;
                    }
                }
                '\n' => break,
                _ => {}
            }
        }
        if let Some(k) = end {
            // a title after the target: [x](path "title")
            let target = rest[..k]
                .split_whitespace()
                .next()
                .unwrap_or("")
                .to_string();
            out.push((at, target));
        }
    }
    out
}

/// GitHub's anchor of a heading: lowercase, spaces to `-`, punctuation dropped.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

/// The anchors of a Markdown file's headings (outside code blocks).
fn anchors(path: &Path) -> BTreeSet<String> {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    prose(&text)
        .lines()
        .filter_map(|l| {
            let t = l.trim_start();
            let hashes = t.chars().take_while(|&c| c == '#').count();
            (1..=6)
                .contains(&hashes)
                .then(|| t[hashes..].strip_prefix(' '))
                .flatten()
                .map(slug)
        })
        .collect()
}

/// The repository path a backticked token names, if it names one.
fn repo_path(token: &str) -> Option<String> {
    if token.is_empty() || token.contains([' ', '<', '*', '{']) {
        return None;
    }
    let mut t = token.split('#').next().unwrap_or("");
    // a trailing `:line` or `:line-line`
    if let Some((head, tail)) = t.rsplit_once(':') {
        if !tail.is_empty() && tail.chars().all(|c| c.is_ascii_digit() || c == '-') {
            t = head;
        }
    }
    let t = t.trim_end_matches(['.', ',', ';', ':', ')', '\'', '"']);
    let named = t.contains('/')
        && (PREFIXES.iter().any(|p| t.starts_with(p)) || EXTENSIONS.iter().any(|e| t.ends_with(e)));
    named.then(|| t.to_string())
}

/// Problems with the links and paths of one document.
fn check_paths(doc: &str) -> (Vec<String>, usize) {
    let text = std::fs::read_to_string(root().join(doc)).unwrap_or_else(|e| panic!("{doc}: {e}"));
    let text = prose(&text);
    let spans = code_spans(&text);
    let dir = Path::new(doc).parent().unwrap_or(Path::new(""));
    let mut problems = Vec::new();
    let mut checked = 0;
    for (at, target) in links(&text, &spans) {
        let line = line_of(&text, at);
        if target.is_empty() || target.contains("://") || target.starts_with("mailto:") {
            continue;
        }
        checked += 1;
        let (file, anchor) = target.split_once('#').unwrap_or((&target, ""));
        let resolved: PathBuf = if file.is_empty() {
            root().join(doc)
        } else {
            root().join(dir).join(file)
        };
        if !resolved.exists() {
            problems.push(format!(
                "{doc}:{line}: link ({target}): {} does not exist",
                dir.join(file).display()
            ));
            continue;
        }
        if !anchor.is_empty()
            && resolved.extension().is_some_and(|e| e == "md")
            && !anchors(&resolved).contains(anchor)
        {
            problems.push(format!(
                "{doc}:{line}: link ({target}): no heading of {} has the anchor #{anchor}",
                dir.join(file).display()
            ));
        }
    }
    for (range, token) in &spans {
        let Some(path) = repo_path(token) else {
            continue;
        };
        checked += 1;
        let full = root().join(&path);
        let ok = if path.ends_with('/') {
            full.is_dir()
        } else {
            full.exists()
        };
        if !ok {
            problems.push(format!(
                "{doc}:{}: `{token}`: the path {path} is not in the repository",
                line_of(&text, range.start)
            ));
        }
    }
    (problems, checked)
}

/// Every `.rs` file under `dir`.
fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let p = e.unwrap().path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The text of every source file under `src/`, concatenated.
fn source() -> String {
    let mut files = Vec::new();
    rust_files(&root().join("src"), &mut files);
    files.sort();
    files
        .iter()
        .map(|f| std::fs::read_to_string(f).unwrap())
        .collect::<Vec<_>>()
        .join("\n")
}

fn is_ident(s: &str) -> bool {
    let mut c = s.chars();
    c.next()
        .is_some_and(|f| f.is_ascii_alphabetic() || f == '_')
        && c.all(|x| x.is_ascii_alphanumeric() || x == '_')
}

fn is_camel(s: &str) -> bool {
    is_ident(s)
        && s.starts_with(|c: char| c.is_ascii_uppercase())
        && s.chars().any(|c| c.is_ascii_lowercase())
        && !s.contains('_')
}

fn is_constant(s: &str) -> bool {
    is_ident(s)
        && s.chars().filter(|c| c.is_ascii_uppercase()).count() >= 2
        && !s.chars().any(|c| c.is_ascii_lowercase())
}

fn is_lower(s: &str) -> bool {
    is_ident(s) && s.starts_with(|c: char| c.is_ascii_lowercase() || c == '_')
}

/// `keyword name` followed by one of `after` somewhere in `src`.
fn defined(src: &str, keyword: &str, name: &str, after: &[char]) -> bool {
    let needle = format!("{keyword} {name}");
    src.match_indices(&needle).any(|(i, _)| {
        let before_ok = src[..i]
            .chars()
            .next_back()
            .is_none_or(|c| !c.is_ascii_alphanumeric() && c != '_');
        let next = src[i + needle.len()..].chars().next();
        before_ok && next.is_some_and(|c| after.contains(&c))
    })
}

/// `name` as a whole word somewhere in `src`.
fn has_word(src: &str, name: &str) -> bool {
    let word = |c: char| c.is_ascii_alphanumeric() || c == '_';
    src.match_indices(name).any(|(i, _)| {
        src[..i].chars().next_back().is_none_or(|c| !word(c))
            && src[i + name.len()..]
                .chars()
                .next()
                .is_none_or(|c| !word(c))
    })
}

fn is_fn(src: &str, name: &str) -> bool {
    defined(src, "fn", name, &['(', '<'])
}

fn is_type(src: &str, name: &str) -> bool {
    ["struct", "enum", "trait", "type"]
        .iter()
        .any(|k| defined(src, k, name, &[' ', '<', '(', ';', '{', '\n', ':', '=']))
}

fn is_const(src: &str, name: &str) -> bool {
    ["const", "static"]
        .iter()
        .any(|k| defined(src, k, name, &[':']))
}

fn is_mod(src: &str, name: &str) -> bool {
    OUTER_MODULES.contains(&name) || defined(src, "mod", name, &[';', ' ', '{'])
}

/// Why the Rust name `token` (a backticked token of a page) is not in `src`, if it is
/// a Rust name at all and is not there. `None` when it is found or is no Rust name.
fn missing_symbol(src: &str, token: &str) -> Option<String> {
    // a call: `name()`, `Type::name()`, `module::name(args)`
    if let Some(open) = token.find('(').filter(|_| token.ends_with(')')) {
        let head = &token[..open];
        let segments: Vec<&str> = head.split("::").collect();
        if !segments.iter().all(|s| is_ident(s)) {
            return None;
        }
        let last = *segments.last().unwrap();
        if !is_lower(last) {
            return None; // `V(s)`: notation, not a call
        }
        return check_path(src, &segments[..segments.len() - 1])
            .or_else(|| (!is_fn(src, last)).then(|| format!("no `fn {last}` in src/")));
    }
    // `prefix::{A, B}`: each in turn
    if let Some((prefix, list)) = token.split_once("::{") {
        let list = list.strip_suffix('}')?;
        if !prefix.split("::").all(is_ident) {
            return None;
        }
        return list
            .split(',')
            .map(str::trim)
            .find_map(|item| missing_symbol(src, &format!("{prefix}::{item}")));
    }
    let segments: Vec<&str> = token.split("::").collect();
    if !segments.iter().all(|s| is_ident(s)) {
        return None;
    }
    if segments.len() == 1 {
        let name = segments[0];
        return if is_camel(name) {
            (!is_type(src, name))
                .then(|| format!("no `struct`, `enum`, `trait` or `type` {name} in src/"))
        } else if is_constant(name) {
            (!is_const(src, name)).then(|| format!("no `const` or `static` {name} in src/"))
        } else if is_lower(name) && name.contains('_') {
            // a snake_case name without parentheses (a function, field or key): at
            // least the word must occur in the source
            (!has_word(src, name)).then(|| format!("the word {name} occurs nowhere in src/"))
        } else {
            None
        };
    }
    let (last, before) = segments.split_last().unwrap();
    if let Some(why) = check_path(src, before) {
        return Some(why);
    }
    let owner = *before.last().unwrap();
    if last.starts_with(|c: char| c.is_ascii_uppercase()) && !is_constant(last) {
        let variant = format!("{owner}::{last}");
        (!is_type(src, last) && !has_word(src, &variant))
            .then(|| format!("{variant} is neither a type nor written anywhere in src/"))
    } else if is_constant(last) {
        (!is_const(src, last)).then(|| format!("no `const` or `static` {last} in src/"))
    } else {
        (!is_fn(src, last) && !is_mod(src, last))
            .then(|| format!("no `fn {last}` or `mod {last}` in src/"))
    }
}

/// Why the leading segments of a path (modules, then types) are not in `src`.
fn check_path(src: &str, segments: &[&str]) -> Option<String> {
    segments.iter().find_map(|s| {
        if is_camel(s) {
            (!is_type(src, s))
                .then(|| format!("no `struct`, `enum`, `trait` or `type` {s} in src/"))
        } else {
            (!is_mod(src, s)).then(|| format!("no `mod {s}` in src/"))
        }
    })
}

#[test]
fn every_link_and_repository_path_in_the_docs_exists() {
    let mut problems = Vec::new();
    let mut checked = 0;
    for doc in documents() {
        let (p, n) = check_paths(&doc);
        problems.extend(p);
        checked += n;
    }
    assert!(
        checked > 50,
        "only {checked} links and paths found: is the scanner broken?"
    );
    assert!(
        problems.is_empty(),
        "{} link(s) or path(s) in the docs point at nothing:\n{}",
        problems.len(),
        problems.join("\n")
    );
}

#[test]
fn every_rust_name_in_extending_md_is_in_the_source() {
    let src = source();
    let mut problems = Vec::new();
    let mut checked = 0;
    for doc in SYMBOL_PAGES {
        let text = prose(&std::fs::read_to_string(root().join(doc)).unwrap());
        for (range, token) in code_spans(&text) {
            checked += 1;
            if let Some(why) = missing_symbol(&src, &token) {
                problems.push(format!(
                    "{doc}:{}: `{token}`: {why}",
                    line_of(&text, range.start)
                ));
            }
        }
    }
    assert!(
        checked > 50,
        "only {checked} code spans found in {SYMBOL_PAGES:?}"
    );
    assert!(
        problems.is_empty(),
        "{} Rust name(s) in the docs are not in src/:\n{}",
        problems.len(),
        problems.join("\n")
    );
}

#[test]
fn the_scanners_read_markdown_as_written() {
    let text = "a `src/lib.rs:12`, ``x ` y`` and [l](docs/methods.md#defaults \"t\")\n\
                ```sh\n`src/nothing.rs`\n```\n`unclosed";
    let p = prose(text);
    let spans = code_spans(&p);
    let tokens: Vec<&str> = spans.iter().map(|(_, t)| t.as_str()).collect();
    assert_eq!(tokens, ["src/lib.rs:12", "x ` y"]);
    assert_eq!(links(&p, &spans)[0].1, "docs/methods.md#defaults");
    assert_eq!(repo_path("src/lib.rs:12"), Some("src/lib.rs".into()));
    assert_eq!(
        repo_path("docs/deploy.md#export)."),
        Some("docs/deploy.md".into())
    );
    assert_eq!(repo_path("runs/x/metrics.csv"), None);
    assert_eq!(repo_path("checkpoints/model_<n>.safetensors"), None);
    assert_eq!(repo_path("policy.onnx"), None);
    assert_eq!(slug("Several processes (MPI)"), "several-processes-mpi");
    assert_eq!(
        slug("Flat ground: the main command (`configs/flat.toml`, seed 1)"),
        "flat-ground-the-main-command-configsflattoml-seed-1"
    );

    let src = "pub struct Foo;\npub enum Kind { A, Beta }\nfn bar(x: u8) {}\nmod baz;\n\
               const LIMIT: u8 = 1;\nlet snake_case = (Kind::A, Kind::Beta);";
    for ok in [
        "Foo",
        "bar()",
        "Foo::bar()",
        "baz::bar(1, 2)",
        "rall::baz::Foo",
        "Kind::A",
        "Kind::Beta",
        "LIMIT",
        "baz::{Foo, Kind}",
        "u8",
        "plain",
        "snake_case",
        "V(s)",
        "cache.get::<T>()",
        "plain words",
    ] {
        assert_eq!(missing_symbol(src, ok), None, "{ok}");
    }
    for bad in [
        "Qux",
        "qux()",
        "Foo::qux()",
        "nomod::bar()",
        "Kind::B",
        "Kind::Gamma",
        "MISSING",
        "plots_list",
        "baz::{Foo, Qux}",
        "foobar()",
    ] {
        assert!(missing_symbol(src, bad).is_some(), "{bad} passed");
    }
}
