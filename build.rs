//! Generates the raw MuJoCo 2.2 FFI with bindgen over Debian's `libmujoco-dev`.
//!
//! Nothing is vendored or downloaded: when the header is missing the build stops
//! with the Debian packages to install.

use std::env;
use std::path::{Path, PathBuf};

/// C wrappers that let a MuJoCo error leave MuJoCo (src/sim/shim.c).
const SHIM: &str = "src/sim/shim.c";

const INSTALL_HINT: &str = "install them with: sudo apt-get install -y libmujoco-dev libclang-dev";

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=MUJOCO_INCLUDE_DIR");
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

fn fail(msg: &str) -> ! {
    eprintln!("error: {msg}");
    println!("cargo:warning={msg}");
    std::process::exit(1);
}
