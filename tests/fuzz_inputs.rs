//! Fuzzing what a user hands over: run configs (random text and mutated valid
//! configs) and checkpoints (mutated, truncated and spliced valid files). Every
//! input must give `Ok` or an error, never a panic.
//!
//! Cases per property: `RALL_FUZZ_CASES` (default 2000, what the suite runs);
//! a long pass: `RALL_FUZZ_CASES=200000 cargo test --release --test fuzz_inputs`.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;

use proptest::prelude::*;
use proptest::test_runner::{Config, TestRunner};
use rall::config::TrainConfig;
use rall::env::terrain::TerrainKind;
use rall::learn::{CriticKind, Learner};
use rall::runner::{load_policy, save_policy, Progress};

fn cases() -> u32 {
    std::env::var("RALL_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2000)
}

fn runner() -> TestRunner {
    TestRunner::new(Config {
        cases: cases(),
        failure_persistence: None,
        ..Config::default()
    })
}

/// Tokens that break parsers and validators: numbers out of range, NaN and
/// infinities, wrong types, unbalanced brackets and quotes, unknown keys.
const TOKENS: &[&str] = &[
    "nan",
    "inf",
    "-inf",
    "-1",
    "0",
    "1e40",
    "-0.0",
    "1.5",
    "\"x\"",
    "[",
    "]",
    "{",
    "}",
    "=",
    "\n",
    "[[",
    "true",
    "[]",
    "[0, 0]",
    "[1e9, 1e9, 1e9]",
    "\"iqn\"",
    "\"scalar\"",
    "\"rough\"",
    "num_envs",
    "cvar_eta",
    "distortion",
    "{ kind = \"wang\", lambda = nan }",
    "#",
    "\"",
    "'",
    "\u{0}",
    "é",
    "18446744073709551616",
    "-9223372036854775809",
];

fn repo_configs() -> Vec<String> {
    [
        "configs/flat.toml",
        "configs/rall.toml",
        "configs/dr.toml",
        "configs/rma.toml",
    ]
    .iter()
    .map(|p| std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(p)).unwrap())
    .collect()
}

/// Replaces `text[at..at + len]` (clamped to char boundaries) with `token`.
fn splice(text: &str, at: usize, len: usize, token: &str) -> String {
    let mut a = at.min(text.len());
    while !text.is_char_boundary(a) {
        a -= 1;
    }
    let mut b = (a + len).min(text.len());
    while !text.is_char_boundary(b) {
        b += 1;
    }
    format!("{}{}{}", &text[..a], token, &text[b..])
}

/// Parses `text`; a panic fails the property with the input.
fn parse_no_panic(text: &str) -> Result<(), TestCaseError> {
    match catch_unwind(AssertUnwindSafe(|| TrainConfig::from_toml_str(text))) {
        Ok(Ok(cfg)) => {
            // an accepted config validates again after a round trip
            let again = TrainConfig::from_toml_str(&cfg.to_toml());
            prop_assert!(
                again.is_ok(),
                "accepted config does not round-trip: {again:?}"
            );
            Ok(())
        }
        Ok(Err(e)) => {
            let message = format!("{e:#}");
            prop_assert!(!message.is_empty());
            Ok(())
        }
        Err(_) => Err(TestCaseError::fail(format!("panic on config:\n{text}"))),
    }
}

#[test]
fn random_text_never_panics_the_config_parser() {
    runner()
        .run(&".{0,400}", |text| parse_no_panic(&text))
        .unwrap();
}

#[test]
fn mutated_valid_configs_never_panic_the_config_parser() {
    let configs = repo_configs();
    let strategy = (
        0..configs.len(),
        prop::collection::vec((any::<usize>(), 0usize..12, 0..TOKENS.len()), 1..6),
    );
    runner()
        .run(&strategy, |(which, edits)| {
            let mut text = configs[which].clone();
            for (at, len, tok) in edits {
                let at = at % (text.len() + 1);
                text = splice(&text, at, len, TOKENS[tok]);
            }
            parse_no_panic(&text)
        })
        .unwrap();
}

/// A small valid checkpoint's bytes.
fn valid_checkpoint(dir: &Path) -> Vec<u8> {
    let mut cfg = TrainConfig::default();
    cfg.env.terrain.kind = TerrainKind::Flat;
    cfg.learner.critic = CriticKind::Iqn;
    cfg.learner.actor_hidden = vec![8];
    cfg.learner.critic_hidden = vec![8];
    cfg.learner.num_cos = 4;
    cfg.learner.num_taus = 4;
    cfg.learner.num_target_taus = 4;
    cfg.learner.num_value_taus = 4;
    let learner = Learner::new(48, 12, &cfg.learner, 1).unwrap();
    let path = dir.join("valid.safetensors");
    save_policy(&path, &learner, &cfg, &Progress::default()).unwrap();
    std::fs::read(path).unwrap()
}

#[test]
fn mutated_checkpoints_never_panic_the_loader() {
    let dir = tempfile::tempdir().unwrap();
    let valid = valid_checkpoint(dir.path());
    assert!(load_policy(&dir.path().join("valid.safetensors")).is_ok());
    let path = dir.path().join("mutated.safetensors");
    // the JSON header (metadata, shapes, offsets) is where structure lives
    let header_len = 8 + u64::from_le_bytes(valid[..8].try_into().unwrap()) as usize;
    let strategy = (
        prop::collection::vec((any::<usize>(), any::<u8>(), any::<bool>()), 1..8),
        prop::option::of(any::<usize>()),
    );
    runner()
        .run(&strategy, |(flips, truncate)| {
            let mut bytes = valid.clone();
            for (at, value, in_header) in flips {
                let span = if in_header { header_len } else { bytes.len() };
                let i = at % span;
                bytes[i] = value;
            }
            if let Some(t) = truncate {
                bytes.truncate(t % (bytes.len() + 1));
            }
            std::fs::write(&path, &bytes).unwrap();
            let out = catch_unwind(AssertUnwindSafe(|| load_policy(&path)));
            prop_assert!(out.is_ok(), "panic on a mutated checkpoint");
            if let Ok(Err(e)) = out {
                let message = format!("{e:#}");
                prop_assert!(
                    message.contains("mutated.safetensors"),
                    "the error names the file: {}",
                    message
                );
            }
            Ok(())
        })
        .unwrap();
}

/// A checkpoint's contents as compared by the flip tests: tensors (name,
/// shape, bits), state blobs, sorted metadata, whether checksums were verified.
type Decoded = (
    Vec<(String, Vec<usize>, Vec<u32>)>,
    Vec<(String, Vec<u8>)>,
    Vec<(String, String)>,
    bool,
);

/// The decoded contents of a checkpoint file, or `None` when the loader refuses it.
fn decoded(bytes: &[u8]) -> Option<Decoded> {
    let c = rall::learn::decode_checkpoint(bytes, Path::new("flipped.safetensors")).ok()?;
    let tensors = c
        .tensors
        .into_iter()
        .map(|t| {
            (
                t.name,
                t.shape,
                t.data.iter().map(|v| v.to_bits()).collect(),
            )
        })
        .collect();
    let mut meta: Vec<(String, String)> = c.metadata.into_iter().collect();
    meta.sort();
    Some((tensors, c.blobs, meta, c.verified))
}

/// Every single-bit flip anywhere in a small checkpoint (header, metadata, every
/// tensor, the state blobs) is either refused or provably harmless: the file
/// then decodes to exactly the original contents (e.g. a padding space of the
/// JSON header turned into another whitespace). Never a silently different policy.
#[test]
fn every_bit_flip_of_a_checkpoint_is_refused_or_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let valid = valid_checkpoint(dir.path());
    let original = decoded(&valid).expect("the valid checkpoint decodes");
    assert!(original.3, "a new checkpoint carries checksums");
    let (mut refused, mut harmless) = (0usize, 0usize);
    let mut bytes = valid.clone();
    for i in 0..valid.len() {
        for bit in 0..8 {
            bytes[i] ^= 1 << bit;
            match decoded(&bytes) {
                None => refused += 1,
                Some(d) => {
                    assert!(
                        d == original,
                        "flipping bit {bit} of byte {i} (of {}) loads a different checkpoint",
                        valid.len()
                    );
                    harmless += 1;
                }
            }
            bytes[i] = valid[i];
        }
    }
    assert!(refused > 0 && refused + harmless == valid.len() * 8);
}

/// Random multi-byte damage: refused (naming the file) or identical contents.
#[test]
fn random_byte_damage_to_a_checkpoint_is_refused_or_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let valid = valid_checkpoint(dir.path());
    let original = decoded(&valid).unwrap();
    let strategy = prop::collection::vec((any::<usize>(), 1u8..=255), 1..6);
    runner()
        .run(&strategy, |flips| {
            let mut bytes = valid.clone();
            for (at, mask) in &flips {
                let i = at % bytes.len();
                bytes[i] ^= mask;
            }
            if let Some(d) = decoded(&bytes) {
                prop_assert!(
                    d == original,
                    "damage {:?} loads a different checkpoint",
                    flips
                );
            }
            Ok(())
        })
        .unwrap();
}

/// Tokens that stress MuJoCo's MJCF parser and compiler.
const MJCF_TOKENS: &[&str] = &[
    "<",
    ">",
    "/>",
    "</body>",
    "<body>",
    "\"",
    "=",
    "nan",
    "inf",
    "-1",
    "0",
    "1e300",
    "-1e300",
    "<geom/>",
    "<joint/>",
    "type=\"hfield\"",
    "size=\"0 0 0\"",
    "mass=\"-1\"",
    "&amp;",
    "&",
    "<!--",
    "-->",
    "<![CDATA[",
    "]]>",
    "<include file=\"x.xml\"/>",
    "\u{0}",
    "\u{ffff}",
    "name=\"trunk\"",
    "<freejoint/>",
    "<mujoco>",
    "</mujoco>",
    "quat=\"0 0 0 0\"",
];

/// Mutated robot MJCF through the loader: every input loads or gives a named
/// error (the loader's label in the message); never a panic, a crash or an abort.
#[test]
fn mutated_mjcf_never_crashes_the_loader() {
    let xml =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml")).unwrap();
    let strategy = (
        prop::collection::vec((any::<usize>(), 0usize..12, 0..MJCF_TOKENS.len()), 1..5),
        prop::option::of(any::<usize>()),
    );
    let mut runner = TestRunner::new(Config {
        cases: cases().min(400),
        failure_persistence: None,
        ..Config::default()
    });
    runner
        .run(&strategy, |(edits, truncate)| {
            let mut text = xml.clone();
            for (at, len, token) in edits {
                text = splice(&text, at % (text.len() + 1), len, MJCF_TOKENS[token]);
            }
            if let Some(t) = truncate.filter(|t| t % 4 == 0) {
                let mut cut = t % (text.len() + 1);
                while !text.is_char_boundary(cut) {
                    cut -= 1;
                }
                text.truncate(cut);
            }
            let out = catch_unwind(AssertUnwindSafe(|| {
                rall::sim::Model::from_xml_str(&text, "fuzzed-robot.xml")
            }));
            prop_assert!(out.is_ok(), "panic on mutated MJCF");
            if let Ok(Err(e)) = out {
                let message = e.to_string();
                prop_assert!(
                    message.contains("fuzzed-robot.xml"),
                    "the error names the file: {}",
                    message
                );
            }
            Ok(())
        })
        .unwrap();
}
