//! The guarded MuJoCo entry points of `shim.c`: each runs one MuJoCo call after
//! `setjmp`, and MuJoCo's error handler `longjmp`s back into it, so an error
//! leaves MuJoCo (which assumes `mju_error` never returns) instead of letting it
//! carry on with a NULL allocation or an overflowed stack. Each returns 0 on
//! success and 1 on a MuJoCo error, whose text [`last_error`] then holds.
//!
//! Only C frames lie between a `setjmp` and its `longjmp`: the Rust caller is
//! outside the guarded function and is returned to normally.

use std::ffi::{c_char, c_int, CStr};
use std::sync::Once;

use super::ffi::{mjData, mjModel, mjVFS, mjtNum};

extern "C" {
    fn rall_install_error_handler();
    fn rall_last_error() -> *const c_char;
    pub(crate) fn rall_mj_loadXML(
        filename: *const c_char,
        vfs: *const mjVFS,
        error: *mut c_char,
        error_sz: c_int,
        out: *mut *mut mjModel,
    ) -> c_int;
    pub(crate) fn rall_mj_copyModel(src: *const mjModel, out: *mut *mut mjModel) -> c_int;
    pub(crate) fn rall_mj_makeData(m: *const mjModel, out: *mut *mut mjData) -> c_int;
    pub(crate) fn rall_mj_step(m: *const mjModel, d: *mut mjData) -> c_int;
    pub(crate) fn rall_mj_forward(m: *const mjModel, d: *mut mjData) -> c_int;
    pub(crate) fn rall_mj_resetData(m: *const mjModel, d: *mut mjData) -> c_int;
    pub(crate) fn rall_mj_resetDataKeyframe(m: *const mjModel, d: *mut mjData, key: c_int)
        -> c_int;
    pub(crate) fn rall_mj_contactForce(
        m: *const mjModel,
        d: *const mjData,
        id: c_int,
        result: *mut mjtNum,
    ) -> c_int;
}

/// Installs the escaping error handler once per process, before the first
/// MuJoCo call made through this crate.
pub(crate) fn install() {
    static ONCE: Once = Once::new();
    // SAFETY: sets MuJoCo's global error hook to the shim's handler.
    ONCE.call_once(|| unsafe { rall_install_error_handler() });
}

/// The message of the last MuJoCo error raised in a guarded call on this thread.
pub(crate) fn last_error() -> String {
    // SAFETY: a NUL-terminated thread-local buffer of the shim, alive for the thread.
    let text = unsafe { CStr::from_ptr(rall_last_error()) }
        .to_string_lossy()
        .trim()
        .to_string();
    if text.is_empty() {
        "(no message)".into()
    } else {
        text
    }
}

/// Turns a guarded call's return code into a result.
pub(crate) fn check(rc: c_int, call: &'static str) -> super::Result<()> {
    if rc == 0 {
        Ok(())
    } else {
        Err(super::SimError::MuJoCo {
            call,
            message: last_error(),
        })
    }
}
