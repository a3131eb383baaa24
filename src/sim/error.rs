//! Errors of the simulation layer, and MuJoCo's warning hook (the error hook is
//! the C shim's, see `shim.rs`).

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
    /// MuJoCo raised an error inside `call`; it was left through the shim's
    /// `longjmp` (src/sim/shim.c), so MuJoCo did not carry on after it.
    #[error("MuJoCo error in {call}: {message}")]
    MuJoCo { call: &'static str, message: String },
    /// A MuJoCo error interrupted a call on this data; its state is undefined
    /// until the next reset.
    #[error("the data is unusable after a MuJoCo error ({0}); reset it first")]
    NeedsReset(String),
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
    static LAST_WARNING: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Warnings return to MuJoCo normally (it expects them to); the text is kept
/// for [`take_warning`] on this thread.
unsafe extern "C" fn on_mujoco_warning(msg: *const c_char) {
    let text = if msg.is_null() {
        "(no message)".to_string()
    } else {
        // SAFETY: MuJoCo passes a NUL-terminated string valid for the call.
        unsafe { CStr::from_ptr(msg) }
            .to_string_lossy()
            .trim()
            .to_string()
    };
    LAST_WARNING.with(|w| *w.borrow_mut() = Some(text));
}

/// Installs MuJoCo's error handler (the shim's, which leaves MuJoCo through
/// `longjmp`) and warning handler once per process, before the first MuJoCo call.
pub(crate) fn install_handlers() {
    static ONCE: Once = Once::new();
    super::shim::install();
    ONCE.call_once(|| {
        // SAFETY: a plain function pointer read by MuJoCo; set once, before any
        // other MuJoCo call made through this crate.
        unsafe {
            ffi::mju_user_warning = Some(on_mujoco_warning);
        }
    });
}

/// The last MuJoCo warning text raised on this thread, if any.
pub fn take_warning() -> Option<String> {
    LAST_WARNING.with(|w| w.borrow_mut().take())
}
