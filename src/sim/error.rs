//! Errors of the simulation layer, and MuJoCo's error/warning hooks.

use std::cell::RefCell;
use std::ffi::{c_char, CStr};
use std::path::PathBuf;
use std::sync::Once;

use super::ffi;

/// Everything that can go wrong in the simulation layer. Never a panic.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("model file {path} does not exist or is unreadable: {reason}")]
    ModelFile { path: PathBuf, reason: String },
    #[error("MuJoCo could not load {source_name}: {message}")]
    Load {
        source_name: String,
        message: String,
    },
    #[error("MuJoCo error: {0}")]
    MuJoCo(String),
    #[error("{kind} named {name:?} not found in the model")]
    UnknownName { kind: &'static str, name: String },
    #[error("physics became unstable at t = {time_s:.3} s: {warnings}")]
    Unstable { time_s: f64, warnings: String },
    #[error("data was made for a different model ({0})")]
    ModelMismatch(String),
    #[error("invalid argument: {0}")]
    Invalid(String),
}

pub type Result<T> = std::result::Result<T, SimError>;

thread_local! {
    static LAST_ERROR: RefCell<Option<String>> = const { RefCell::new(None) };
    static LAST_WARNING: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// MuJoCo calls this instead of `exit(1)`; the message is turned into a
/// [`SimError::MuJoCo`] by the next [`take_error`] on this thread.
unsafe extern "C" fn on_mujoco_error(msg: *const c_char) {
    let text = message_text(msg);
    LAST_ERROR.with(|e| *e.borrow_mut() = Some(text));
}

unsafe extern "C" fn on_mujoco_warning(msg: *const c_char) {
    let text = message_text(msg);
    LAST_WARNING.with(|w| *w.borrow_mut() = Some(text));
}

unsafe fn message_text(msg: *const c_char) -> String {
    if msg.is_null() {
        return "(no message)".into();
    }
    // SAFETY: MuJoCo passes a NUL-terminated string valid for the call.
    unsafe { CStr::from_ptr(msg) }
        .to_string_lossy()
        .trim()
        .to_string()
}

/// Installs the handlers once per process, before the first MuJoCo call.
pub(crate) fn install_handlers() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // SAFETY: the globals are plain function pointers read by MuJoCo; we set
        // them once, before any other MuJoCo call made through this crate.
        unsafe {
            ffi::mju_user_error = Some(on_mujoco_error);
            ffi::mju_user_warning = Some(on_mujoco_warning);
        }
    });
}

/// The MuJoCo error raised on this thread since the last call, if any.
pub(crate) fn take_error() -> Option<String> {
    LAST_ERROR.with(|e| e.borrow_mut().take())
}

/// The last MuJoCo warning text raised on this thread, if any.
pub fn take_warning() -> Option<String> {
    LAST_WARNING.with(|w| w.borrow_mut().take())
}

pub(crate) fn check_error() -> Result<()> {
    match take_error() {
        Some(msg) => Err(SimError::MuJoCo(msg)),
        None => Ok(()),
    }
}
