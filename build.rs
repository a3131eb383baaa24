//! Generates the raw MuJoCo 2.2 FFI with bindgen over Debian's `libmujoco-dev`.
//!
//! Nothing is vendored or downloaded: when the header is missing the build stops
//! with the Debian packages to install.

use std::env;
use std::path::{Path, PathBuf};

/// C wrappers that let a MuJoCo error leave MuJoCo (src/sim/shim.c).
const SHIM: &str = "src/sim/shim.c";

const INSTALL_HINT: &str = "install them with: sudo apt-get install -y libmujoco-dev libclang-dev";

/// What decides an evaluation rollout's numbers: hashed into the rollout
/// cache's key (`src/eval/cache.rs`). The experiment and command-line code only
/// arrange rollouts (their settings are in each key), so they are left out.
const ROLLOUT_SOURCES: [&str; 3] = ["src", "mjcf", "Cargo.lock"];
const NOT_ROLLOUT_SOURCES: [&str; 3] = ["src/experiment", "src/cli", "src/viz"];

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=MUJOCO_INCLUDE_DIR");
    rollout_fingerprint();
    if env::var_os("CARGO_FEATURE_SIM").is_none() {
        return; // learner-only build: no MuJoCo needed
    }
    let include_dir = env::var("MUJOCO_INCLUDE_DIR").unwrap_or_else(|_| "/usr/include".into());
    let header = Path::new(&include_dir).join("mujoco/mujoco.h");
    if !header.exists() {
        fail(&format!(
            "MuJoCo header not found at {} (MuJoCo 2.2.2 from Debian's `libmujoco-dev` is required; \
             bindgen also needs `libclang-dev`): {INSTALL_HINT}",
            header.display()
        ));
    }
    println!("cargo:rerun-if-changed={}", header.display());
    println!("cargo:rerun-if-changed={SHIM}");
    // The setjmp/longjmp error escape (see the file's header): compiled before
    // the link line for MuJoCo so the static shim resolves against it.
    cc::Build::new()
        .file(SHIM)
        .include(&include_dir)
        .warnings(true)
        .compile("rall_mujoco_shim");
    println!("cargo:rustc-link-lib=dylib=mujoco");

    let bindings = bindgen::Builder::default()
        .header(header.to_string_lossy())
        .clang_arg(format!("-I{include_dir}"))
        .allowlist_function("mj_.*")
        .allowlist_function("mju_.*")
        .allowlist_type("mj[A-Z].*")
        .allowlist_type("mjt.*")
        .allowlist_var("mj.*")
        .derive_default(true)
        .layout_tests(false)
        .generate_comments(false)
        .generate();
    let bindings = match bindings {
        Ok(b) => b,
        Err(e) => fail(&format!(
            "bindgen could not process {} ({e}); is libclang installed? {INSTALL_HINT}",
            header.display()
        )),
    };
    let out = PathBuf::from(env::var("OUT_DIR").expect("cargo sets OUT_DIR")).join("mujoco_ffi.rs");
    if let Err(e) = bindings.write_to_file(&out) {
        fail(&format!("cannot write {}: {e}", out.display()));
    }
}

/// Sets `RALL_ROLLOUT_FINGERPRINT`: FNV-1a (64 bit) over the paths and bytes
/// of every file of [`ROLLOUT_SOURCES`] outside [`NOT_ROLLOUT_SOURCES`], in
/// path order.
fn rollout_fingerprint() {
    let mut files = Vec::new();
    for root in ROLLOUT_SOURCES {
        println!("cargo:rerun-if-changed={root}");
        collect_files(Path::new(root), &mut files);
    }
    files.retain(|f| !NOT_ROLLOUT_SOURCES.iter().any(|n| f.starts_with(n)));
    files.sort();
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for &b in bytes {
            h = (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
        }
    };
    for f in &files {
        eat(f.to_string_lossy().as_bytes());
        match std::fs::read(f) {
            Ok(bytes) => eat(&bytes),
            Err(e) => fail(&format!("cannot read {}: {e}", f.display())),
        }
    }
    println!("cargo:rustc-env=RALL_ROLLOUT_FINGERPRINT={h:016x}");
}

fn collect_files(path: &Path, out: &mut Vec<PathBuf>) {
    if path.is_dir() {
        let Ok(entries) = std::fs::read_dir(path) else {
            fail(&format!("cannot list {}", path.display()))
        };
        for e in entries.flatten() {
            collect_files(&e.path(), out);
        }
    } else if path.is_file() {
        out.push(path.to_path_buf());
    }
}

fn fail(msg: &str) -> ! {
    eprintln!("error: {msg}");
    println!("cargo:warning={msg}");
    std::process::exit(1);
}
