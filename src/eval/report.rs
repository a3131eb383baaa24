//! Writing evaluation tables: Markdown (printed), CSV and JSON beside it.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// A Markdown table from a header and rows (cells already formatted).
/// `right` marks right-aligned columns.
pub fn markdown_table(header: &[String], right: &[bool], rows: &[Vec<String>]) -> String {
    let mut s = String::new();
    s.push_str(&format!("| {} |\n", header.join(" | ")));
    let rule: Vec<&str> = (0..header.len())
        .map(|i| {
            if right.get(i).copied().unwrap_or(false) {
                "---:"
            } else {
                ":---"
            }
        })
        .collect();
    s.push_str(&format!("|{}|\n", rule.join("|")));
    for r in rows {
        s.push_str(&format!("| {} |\n", r.join(" | ")));
    }
    s
}

/// Quotes a CSV field when it needs it.
pub fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// A CSV line from fields.
pub fn csv_line(fields: &[String]) -> String {
    let f: Vec<String> = fields.iter().map(|x| csv_field(x)).collect();
    f.join(",") + "\n"
}

/// Writes `<dir>/<stem>.md`, `.csv` and `.json`; returns their paths.
pub fn write_outputs(
    dir: &Path,
    stem: &str,
    markdown: &str,
    csv: &str,
    json: &serde_json::Value,
) -> Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut out = Vec::new();
    for (ext, text) in [
        ("md", markdown.to_string()),
        ("csv", csv.to_string()),
        ("json", serde_json::to_string_pretty(json)? + "\n"),
    ] {
        let path = dir.join(format!("{stem}.{ext}"));
        crate::fsio::write_atomic(&path, text.as_bytes())?;
        out.push(path);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn markdown_and_csv_shapes() {
        let t = markdown_table(
            &["a".into(), "b".into()],
            &[false, true],
            &[vec!["x".into(), "1".into()]],
        );
        assert_eq!(t, "| a | b |\n|:---|---:|\n| x | 1 |\n");
        assert_eq!(csv_line(&["a,b".into(), "c".into()]), "\"a,b\",c\n");
    }
}
