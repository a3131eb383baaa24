//! The manifest of shipped weights: `policies/MANIFEST` lists every binary the
//! repository ships (checkpoints, ONNX graphs) with its size and SHA-256, so
//! that a changed, lost or unlisted file is found by `rall checkpoint verify`
//! and weight cannot enter the repository unnoticed.
//!
//! Format: one line per file, `<sha256 hex>  <size in bytes>  <path>`, the path
//! relative to the manifest's folder with `/` separators, sorted by path; lines
//! starting with `#` are comments.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::Read;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use sha2::{Digest, Sha256};

/// The manifest's file name inside the folder it describes.
pub const MANIFEST: &str = "MANIFEST";

/// Extensions of the files a manifest must list (binaries).
pub const BINARY_EXTENSIONS: [&str; 2] = ["safetensors", "onnx"];

/// One listed file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Entry {
    pub sha256: String,
    pub size_bytes: u64,
}

/// What a manifest says: path (relative, `/`-separated) -> entry.
pub type Manifest = BTreeMap<String, Entry>;

/// SHA-256 of a file's bytes, as lowercase hex (streamed: big files are not read whole).
pub fn file_sha256(path: &Path) -> Result<String> {
    let mut f = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f
            .read(&mut buf)
            .with_context(|| format!("reading {}", path.display()))?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(h.finalize().iter().fold(String::new(), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    }))
}

/// Whether `path` is a binary a manifest must list.
pub fn is_binary(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| BINARY_EXTENSIONS.contains(&e))
}

/// Every binary under `dir` (recursive), as paths relative to `dir`, sorted.
pub fn binaries_under(dir: &Path) -> Result<Vec<String>> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<String>) -> Result<()> {
        let entries =
            std::fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))?;
        for e in entries {
            let path = e
                .with_context(|| format!("listing {}", dir.display()))?
                .path();
            if path.is_dir() {
                walk(root, &path, out)?;
            } else if is_binary(&path) {
                out.push(relative(root, &path));
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out)?;
    out.sort();
    Ok(out)
}

/// `path` relative to `root`, with `/` separators.
fn relative(root: &Path, path: &Path) -> String {
    let rel = path.strip_prefix(root).unwrap_or(path);
    rel.components()
        .map(|c| c.as_os_str().to_string_lossy())
        .collect::<Vec<_>>()
        .join("/")
}

/// The manifest of every binary under `dir` as it is now.
pub fn measure(dir: &Path) -> Result<Manifest> {
    let mut m = Manifest::new();
    for rel in binaries_under(dir)? {
        let path = dir.join(&rel);
        let size_bytes = std::fs::metadata(&path)
            .with_context(|| format!("reading {}", path.display()))?
            .len();
        let sha256 = file_sha256(&path)?;
        m.insert(rel, Entry { sha256, size_bytes });
    }
    Ok(m)
}

/// The manifest's text: a header comment, then one sorted line per file.
pub fn to_text(m: &Manifest) -> String {
    let total: u64 = m.values().map(|e| e.size_bytes).sum();
    let mut s = format!(
        "# Every binary shipped under this folder: SHA-256, size in bytes, path.\n\
         # {} files, {:.1} MB. Checked by `rall checkpoint verify`; rewritten by\n\
         # `rall checkpoint manifest`.\n",
        m.len(),
        total as f64 / 1e6
    );
    for (path, e) in m {
        let _ = writeln!(s, "{}  {}  {path}", e.sha256, e.size_bytes);
    }
    s
}

/// Parses a manifest's text; `source` names it in errors.
pub fn parse(text: &str, source: &Path) -> Result<Manifest> {
    let mut m = Manifest::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let at = || format!("{} line {}", source.display(), i + 1);
        let parts: Vec<&str> = line.split_whitespace().collect();
        let [sha, size, path] = parts[..] else {
            bail!(
                "{}: expected `<sha256>  <size>  <path>`, found {line:?}",
                at()
            );
        };
        if sha.len() != 64 || !sha.bytes().all(|b| b.is_ascii_hexdigit()) {
            bail!("{}: {sha:?} is not a SHA-256 in hex", at());
        }
        let size_bytes: u64 = size
            .parse()
            .with_context(|| format!("{}: size {size:?} is not a number of bytes", at()))?;
        let entry = Entry {
            sha256: sha.to_ascii_lowercase(),
            size_bytes,
        };
        if m.insert(path.to_string(), entry).is_some() {
            bail!("{}: {path} is listed twice", at());
        }
    }
    Ok(m)
}

/// Reads `dir/MANIFEST`.
pub fn read(dir: &Path) -> Result<Manifest> {
    let path = dir.join(MANIFEST);
    let text = std::fs::read_to_string(&path).with_context(|| {
        format!(
            "reading {} (write it with `rall checkpoint manifest {}`)",
            path.display(),
            dir.display()
        )
    })?;
    parse(&text, &path)
}

/// Writes `dir/MANIFEST` for the binaries under `dir` now; returns it.
pub fn write(dir: &Path) -> Result<Manifest> {
    let m = measure(dir)?;
    crate::fsio::write_atomic(&dir.join(MANIFEST), to_text(&m).as_bytes())?;
    Ok(m)
}

/// One way a folder differs from its manifest.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Problem {
    /// Listed but not on disk.
    Missing(String),
    /// On disk but not listed.
    Unlisted(String),
    /// Listed with another size or hash.
    Changed {
        path: String,
        listed: Entry,
        found: Entry,
    },
}

impl Problem {
    pub fn describe(&self, dir: &Path) -> String {
        match self {
            Problem::Missing(p) => format!(
                "{}: listed in the manifest but missing",
                dir.join(p).display()
            ),
            Problem::Unlisted(p) => format!(
                "{}: a binary the manifest does not list",
                dir.join(p).display()
            ),
            Problem::Changed {
                path,
                listed,
                found,
            } => format!(
                "{}: {} bytes, SHA-256 {} but the manifest lists {} bytes, {}",
                dir.join(path).display(),
                found.size_bytes,
                &found.sha256[..16],
                listed.size_bytes,
                &listed.sha256[..16]
            ),
        }
    }
}

/// Compares `dir` with its manifest: every problem, in path order.
pub fn check(dir: &Path) -> Result<(Manifest, Vec<Problem>)> {
    let listed = read(dir)?;
    let found = measure(dir)?;
    let mut problems = Vec::new();
    for (path, l) in &listed {
        match found.get(path) {
            None => problems.push(Problem::Missing(path.clone())),
            Some(f) if f != l => problems.push(Problem::Changed {
                path: path.clone(),
                listed: l.clone(),
                found: f.clone(),
            }),
            Some(_) => {}
        }
    }
    for path in found.keys().filter(|p| !listed.contains_key(*p)) {
        problems.push(Problem::Unlisted(path.clone()));
    }
    problems.sort_by(|a, b| key(a).cmp(key(b)));
    Ok((listed, problems))
}

fn key(p: &Problem) -> &str {
    match p {
        Problem::Missing(s) | Problem::Unlisted(s) => s,
        Problem::Changed { path, .. } => path,
    }
}

/// Joins a manifest path onto its folder.
pub fn full_path(dir: &Path, rel: &str) -> PathBuf {
    rel.split('/').fold(dir.to_path_buf(), |p, c| p.join(c))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_round_trips_and_bad_lines_are_named() {
        let mut m = Manifest::new();
        m.insert(
            "a/b.safetensors".into(),
            Entry {
                sha256: "ab".repeat(32),
                size_bytes: 12,
            },
        );
        let p = Path::new("MANIFEST");
        assert_eq!(parse(&to_text(&m), p).unwrap(), m);
        let e = parse("xyz 12 a", p).unwrap_err().to_string();
        assert!(e.contains("line 1") && e.contains("not a SHA-256"), "{e}");
        let e = parse(&format!("{} twelve a", "ab".repeat(32)), p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("size"), "{e}");
        let twice = format!("{0} 1 a\n{0} 1 a\n", "ab".repeat(32));
        assert!(parse(&twice, p).unwrap_err().to_string().contains("twice"));
    }

    #[test]
    fn the_sha256_of_abc_is_the_published_one() {
        let dir = std::env::temp_dir().join(format!("rall-manifest-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("abc");
        std::fs::write(&f, b"abc").unwrap();
        assert_eq!(
            file_sha256(&f).unwrap(),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
