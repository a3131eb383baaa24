//! The simulation layer: safe types over MuJoCo 2.2.2. The only module with `unsafe`.
//!
//! - [`Model`] loads MJCF from a path or a string; MuJoCo's errors become [`SimError`].
//! - [`Data`] holds the state; [`Data::step`] reports instability instead of
//!   continuing on NaN.
//! - MuJoCo's error and warning handlers are installed on first use. Every MuJoCo
//!   entry point that can raise an error runs inside a C wrapper (`shim.c`) whose
//!   `setjmp` the error handler `longjmp`s back to, so an error leaves MuJoCo
//!   (which assumes `mju_error` never returns) and becomes [`SimError::MuJoCo`].
//! - A [`Data`] only runs with models of the family it was made for.

mod data;
mod error;
mod ffi;
mod model;
mod shim;

pub use data::{raw_bench, ArenaUse, Contact, Data, Warnings};
pub use error::{take_warning, Result, SimError};
pub use model::{GeomShape, JointKind, Model, ObjKind};

/// MuJoCo's library version (222 for 2.2.2).
pub fn mujoco_version() -> i32 {
    // SAFETY: no arguments, pure.
    unsafe { ffi::mj_version() }
}

/// MuJoCo's library version as text ("2.2.2"), read from the linked library.
pub fn mujoco_version_string() -> String {
    // SAFETY: no arguments; MuJoCo returns a pointer to a static NUL-terminated string.
    let text = unsafe { ffi::mj_versionString() };
    if text.is_null() {
        return mujoco_version().to_string();
    }
    // SAFETY: non-null, NUL-terminated and static (never freed), checked above.
    unsafe { std::ffi::CStr::from_ptr(text) }
        .to_string_lossy()
        .into_owned()
}
