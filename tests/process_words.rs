//! The repository speaks of the project alone: no tracked file refers to the working
//! sittings it was written in, to tracker numbers, or to notes kept outside the
//! repository. Every file `git ls-files` lists is read (binary files and files over
//! `MAX_BYTES` aside) and each of its lines is checked, case-insensitively, for the
//! patterns `offending` names: a word for a working sitting (singular or plural, as a
//! word of its own, so onnxruntime's class name passes), the tracker's word followed
//! by a number, a path into the folder shared beside the checkout, and the name or
//! the sections of the notes on the design kept there.
//!
//! The patterns are built from pieces so that this file does not match itself. The
//! test is skipped, saying why, when git or the repository's `.git` is missing (an
//! unpacked source archive); CI runs on a fresh clone, where both exist.

use std::path::Path;
use std::process::Command;

/// Files larger than this are data, not prose (the biggest text files tracked, the
/// campaign's `metrics.csv`, are about 2 MB).
const MAX_BYTES: u64 = 4 << 20;

/// Extensions of binary files, never read.
const BINARY: [&str; 5] = ["safetensors", "png", "gz", "rrd", "onnx"];

fn is_word(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// Byte offsets of every occurrence of `needle` in `hay`.
fn occurrences<'a>(hay: &'a str, needle: &'a str) -> impl Iterator<Item = usize> + 'a {
    hay.match_indices(needle).map(|(i, _)| i)
}

/// What `line` matches, if anything: the name of the first pattern found.
fn offending(line: &str) -> Option<&'static str> {
    // ASCII lowercasing keeps every byte offset, so slices of `low` are slices of `line`.
    let low = line.to_ascii_lowercase();
    let word = concat!("ses", "sion");
    for i in occurrences(&low, word) {
        let before = low[..i].chars().next_back();
        let rest = &low[i + word.len()..];
        let mut after = rest.chars();
        let next = after.next();
        let ends = match next {
            None => true,
            Some('s') => after.next().is_none_or(|c| !is_word(c)),
            Some(c) => !is_word(c),
        };
        if before.is_none_or(|c| !is_word(c)) && ends {
            return Some(concat!("the word ses", "sion(s)"));
        }
    }
    let tracker = concat!("iss", "ue");
    for i in occurrences(&low, tracker) {
        let mut rest = &low.as_bytes()[i + tracker.len()..];
        if rest.first() == Some(&b' ') {
            rest = &rest[1..];
        }
        if rest.first() == Some(&b'#') {
            rest = &rest[1..];
        }
        if rest.first().is_some_and(u8::is_ascii_digit) {
            return Some(concat!("iss", "ue and a number"));
        }
    }
    let fixed: [(&str, &'static str); 4] = [
        (
            concat!("../", "shared"),
            concat!("a path into ../", "shared"),
        ),
        (concat!("design", ".md"), concat!("design", ".md")),
        (concat!("design", " section"), concat!("design", " section")),
        (concat!("design", " note"), concat!("design", " note")),
    ];
    fixed
        .iter()
        .find(|(needle, _)| low.contains(needle))
        .map(|&(_, name)| name)
}

#[test]
fn the_patterns_catch_what_they_should_and_nothing_else() {
    let s = concat!("Ses", "sion");
    let caught = [
        format!("{s} 17 raised the budget"),
        format!("the {}s of a week", s.to_lowercase()),
        format!("(end of the {s})"),
        format!("a {}-19 section", s.to_lowercase()),
        concat!("see Iss", "ue 9, item 5").to_string(),
        concat!("fixes iss", "ue #12").to_string(),
        concat!("iss", "ue9").to_string(),
        concat!("from ../", "shared/tools/x").to_string(),
        concat!("Design", ".md section 4").to_string(),
        concat!("per design", " section 5").to_string(),
        concat!("a design", " note says").to_string(),
    ];
    for line in &caught {
        assert!(offending(line).is_some(), "not caught: {line}");
    }
    let passed = [
        format!("ort.Inference{s}(path)"),
        format!("{}_id = 3", s.to_lowercase()),
        format!("{}al data", s.to_lowercase()),
        concat!("known iss", "ues: none").to_string(),
        concat!("an iss", "ue with it").to_string(),
        "shared model per worker thread".to_string(),
        "design of the learner".to_string(),
    ];
    for line in &passed {
        assert_eq!(offending(line), None, "caught: {line}");
    }
}

#[test]
fn no_tracked_file_speaks_of_the_process() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    if !root.join(".git").exists() {
        eprintln!(
            "skipped: {} has no .git (not a git checkout)",
            root.display()
        );
        return;
    }
    let out = match Command::new("git")
        .args(["ls-files", "-z"])
        .current_dir(root)
        .output()
    {
        Ok(out) => out,
        Err(e) => {
            eprintln!("skipped: cannot run git ({e})");
            return;
        }
    };
    if !out.status.success() {
        eprintln!(
            "skipped: git ls-files failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        );
        return;
    }
    let listing = String::from_utf8_lossy(&out.stdout);
    let mut hits = Vec::new();
    let mut read = 0;
    for rel in listing.split('\0').filter(|p| !p.is_empty()) {
        let path = root.join(rel);
        let binary = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| BINARY.contains(&e.to_ascii_lowercase().as_str()));
        if binary {
            continue;
        }
        // A tracked file removed from the working tree (a rename not yet committed)
        // has nothing to read.
        let Ok(meta) = std::fs::metadata(&path) else {
            continue;
        };
        if !meta.is_file() || meta.len() > MAX_BYTES {
            continue;
        }
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("reading {rel}: {e}"));
        if bytes.contains(&0) {
            continue;
        }
        read += 1;
        let text = String::from_utf8_lossy(&bytes);
        for (n, line) in text.lines().enumerate() {
            if let Some(what) = offending(line) {
                hits.push(format!("{rel}:{}: {what}: {}", n + 1, line.trim()));
            }
        }
    }
    assert!(read > 0, "git ls-files listed no readable file");
    assert!(
        hits.is_empty(),
        "{} line(s) speak of the process rather than the project; say the fact itself \
         (or date it in docs/research-log.md):\n{}",
        hits.len(),
        hits.join("\n")
    );
}
