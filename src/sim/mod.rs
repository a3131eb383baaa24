//! The simulation layer: safe types over MuJoCo 2.2.2. The only module with `unsafe`.
//!
//! - [`Model`] loads MJCF from a path or a string; MuJoCo's errors become [`SimError`].
//! - [`Data`] holds the state; [`Data::step`] reports instability instead of
//!   continuing on NaN.
//! - MuJoCo's error and warning handlers are installed on first use, so a MuJoCo
//!   error never aborts the process.

mod data;
mod error;
mod ffi;
mod model;

pub use data::{raw_bench, Contact, Data, Warnings};
pub use error::{take_warning, Result, SimError};
pub use model::{GeomShape, JointKind, Model, ObjKind};

/// MuJoCo's library version (222 for 2.2.2).
pub fn mujoco_version() -> i32 {
    // SAFETY: no arguments, pure.
    unsafe { ffi::mj_version() }
}
