//! [`Data`]: the simulation state of one model (`mjData`).

use std::ptr::NonNull;

use super::error::{check_error, Result, SimError};
use super::ffi;
use super::model::{Model, ObjKind};

/// The sizes a `Data` was made for; checked on every call that takes a model so
/// a `Data` can never be stepped with an incompatible model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Shape {
    nq: i32,
    nv: i32,
    nu: i32,
    na: i32,
    nbody: i32,
    ngeom: i32,
    nstack: i32,
    nconmax: i32,
    njmax: i32,
}

impl Shape {
    fn of(m: &Model) -> Shape {
        // SAFETY: valid model pointer for the call.
        let m = unsafe { &*m.raw() };
        Shape {
            nq: m.nq,
            nv: m.nv,
            nu: m.nu,
            na: m.na,
            nbody: m.nbody,
            ngeom: m.ngeom,
            nstack: m.nstack,
            nconmax: m.nconmax,
            njmax: m.njmax,
        }
    }
}

/// One contact as MuJoCo reports it.
#[derive(Debug, Clone, Copy)]
pub struct Contact {
    pub index: usize,
    pub geom1: usize,
    pub geom2: usize,
    /// Signed distance (m); negative is penetration.
    pub dist_m: f64,
    /// Contact point in world coordinates (m).
    pub pos_m: [f64; 3],
    /// Contact normal (world frame), pointing from geom1 to geom2.
    pub normal: [f64; 3],
}

/// Counts of MuJoCo's warnings, by kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Warnings {
    pub counts: [i32; ffi::mjtWarning__mjNWARNING as usize],
}

const WARNING_NAMES: [&str; ffi::mjtWarning__mjNWARNING as usize] = [
    "near-singular inertia",
    "contact list full",
    "constraint list full",
    "visual geom list full",
    "bad qpos",
    "bad qvel",
    "bad qacc",
    "bad ctrl",
];

impl Warnings {
    pub fn total(&self) -> i64 {
        self.counts.iter().map(|&c| c as i64).sum()
    }

    /// Warnings that mean the state is no longer trustworthy (MuJoCo resets the
    /// data itself on bad qpos/qvel/qacc; a full contact list drops contacts).
    pub fn unstable_since(&self, before: &Warnings) -> bool {
        use ffi::*;
        [
            mjtWarning__mjWARN_BADQPOS,
            mjtWarning__mjWARN_BADQVEL,
            mjtWarning__mjWARN_BADQACC,
            mjtWarning__mjWARN_BADCTRL,
            mjtWarning__mjWARN_CONTACTFULL,
            mjtWarning__mjWARN_CNSTRFULL,
            mjtWarning__mjWARN_INERTIA,
        ]
        .iter()
        .any(|&w| self.counts[w as usize] > before.counts[w as usize])
    }

    /// Human-readable list of the warnings that grew since `before`.
    pub fn describe_since(&self, before: &Warnings) -> String {
        let parts: Vec<String> = (0..self.counts.len())
            .filter(|&i| self.counts[i] > before.counts[i])
            .map(|i| {
                format!(
                    "{} x{}",
                    WARNING_NAMES[i],
                    self.counts[i] - before.counts[i]
                )
            })
            .collect();
        if parts.is_empty() {
            "none".into()
        } else {
            parts.join(", ")
        }
    }
}

/// Owned simulation state. Freed on drop; `Send` (one thread at a time).
pub struct Data {
    ptr: NonNull<ffi::mjData>,
    shape: Shape,
    warnings_seen: Warnings,
}

// SAFETY: mjData has no thread affinity; &mut self gives exclusive access.
unsafe impl Send for Data {}

impl Drop for Data {
    fn drop(&mut self) {
        // SAFETY: we own the pointer from mj_makeData.
        unsafe { ffi::mj_deleteData(self.ptr.as_ptr()) }
    }
}

impl Data {
    /// Allocates state for `model`, at the model's default pose.
    pub fn new(model: &Model) -> Result<Data> {
        // SAFETY: valid model.
        let raw = unsafe { ffi::mj_makeData(model.raw()) };
        check_error()?;
        let ptr = NonNull::new(raw)
            .ok_or_else(|| SimError::MuJoCo("mj_makeData returned null".into()))?;
        let mut data = Data {
            ptr,
            shape: Shape::of(model),
            warnings_seen: Warnings::default(),
        };
        data.forward(model)?;
        Ok(data)
    }

    fn check_model(&self, model: &Model) -> Result<()> {
        let other = Shape::of(model);
        if other == self.shape {
            Ok(())
        } else {
            Err(SimError::ModelMismatch(format!(
                "data {:?} vs model {:?}",
                self.shape, other
            )))
        }
    }

    fn d(&self) -> &ffi::mjData {
        // SAFETY: valid for self's lifetime.
        unsafe { self.ptr.as_ref() }
    }

    /// One physics step (`mj_step`). Fails, instead of silently continuing, when
    /// MuJoCo flags a bad state (NaN/huge qacc, qpos, qvel: MuJoCo then resets the
    /// data) or a full contact/constraint list; the caller should reset.
    #[inline]
    pub fn step(&mut self, model: &Model) -> Result<()> {
        self.check_model(model)?;
        // SAFETY: model and data match in shape (checked above).
        unsafe { ffi::mj_step(model.raw(), self.ptr.as_ptr()) };
        self.after_call()
    }

    /// Recomputes derived quantities (kinematics, contacts, forces) without integrating.
    pub fn forward(&mut self, model: &Model) -> Result<()> {
        self.check_model(model)?;
        // SAFETY: as in step.
        unsafe { ffi::mj_forward(model.raw(), self.ptr.as_ptr()) };
        self.after_call()
    }

    #[inline]
    fn after_call(&mut self) -> Result<()> {
        check_error()?;
        let now = self.warnings();
        if now != self.warnings_seen {
            let before = self.warnings_seen;
            self.warnings_seen = now;
            if now.unstable_since(&before) {
                return Err(SimError::Unstable {
                    time_s: self.time_s(),
                    warnings: now.describe_since(&before),
                });
            }
        }
        Ok(())
    }

    /// Resets to the model's default state (qpos0, zero velocity).
    pub fn reset(&mut self, model: &Model) -> Result<()> {
        self.check_model(model)?;
        // SAFETY: matching model and data.
        unsafe { ffi::mj_resetData(model.raw(), self.ptr.as_ptr()) };
        self.warnings_seen = Warnings::default();
        self.forward(model)
    }

    /// Resets to the keyframe called `name`.
    pub fn reset_to_keyframe(&mut self, model: &Model, name: &str) -> Result<()> {
        self.check_model(model)?;
        let key = model.require_id(ObjKind::Key, name)?;
        // SAFETY: matching model and data, key id in range.
        unsafe { ffi::mj_resetDataKeyframe(model.raw(), self.ptr.as_ptr(), key as i32) };
        self.warnings_seen = Warnings::default();
        self.forward(model)
    }

    /// Warning counters since the last reset.
    pub fn warnings(&self) -> Warnings {
        let mut w = Warnings::default();
        for (i, stat) in self.d().warning.iter().enumerate() {
            w.counts[i] = stat.number;
        }
        w
    }

    /// Simulated time (s).
    pub fn time_s(&self) -> f64 {
        self.d().time
    }
    pub fn set_time_s(&mut self, t: f64) {
        // SAFETY: exclusive access.
        unsafe { self.ptr.as_mut() }.time = t;
    }

    pub fn qpos(&self) -> &[f64] {
        self.reals(self.d().qpos, self.shape.nq)
    }
    pub fn qpos_mut(&mut self) -> &mut [f64] {
        self.reals_mut(self.d().qpos, self.shape.nq)
    }
    pub fn qvel(&self) -> &[f64] {
        self.reals(self.d().qvel, self.shape.nv)
    }
    pub fn qvel_mut(&mut self) -> &mut [f64] {
        self.reals_mut(self.d().qvel, self.shape.nv)
    }
    pub fn qacc(&self) -> &[f64] {
        self.reals(self.d().qacc, self.shape.nv)
    }
    pub fn ctrl(&self) -> &[f64] {
        self.reals(self.d().ctrl, self.shape.nu)
    }
    pub fn ctrl_mut(&mut self) -> &mut [f64] {
        self.reals_mut(self.d().ctrl, self.shape.nu)
    }
    /// Generalised actuator forces (N m for hinges), one per dof.
    pub fn qfrc_actuator(&self) -> &[f64] {
        self.reals(self.d().qfrc_actuator, self.shape.nv)
    }
    /// Cartesian force/torque applied to each body (world frame, at the body's
    /// centre of mass, as MuJoCo defines it): [fx fy fz tx ty tz].
    pub fn xfrc_applied_mut(&mut self) -> &mut [[f64; 6]] {
        let n = self.shape.nbody as usize;
        // SAFETY: xfrc_applied holds 6*nbody reals.
        unsafe { std::slice::from_raw_parts_mut(self.d().xfrc_applied as *mut [f64; 6], n) }
    }
    /// Cartesian force/torque applied to each body, read-only.
    pub fn xfrc_applied(&self) -> &[[f64; 6]] {
        let n = self.shape.nbody as usize;
        // SAFETY: xfrc_applied holds 6*nbody reals.
        unsafe { std::slice::from_raw_parts(self.d().xfrc_applied as *const [f64; 6], n) }
    }
    /// Body origin positions (world, m).
    pub fn xpos(&self) -> &[[f64; 3]] {
        let n = self.shape.nbody as usize;
        // SAFETY: xpos holds 3*nbody reals.
        unsafe { std::slice::from_raw_parts(self.d().xpos as *const [f64; 3], n) }
    }
    /// Body orientations (world, unit quaternion w x y z).
    pub fn xquat(&self) -> &[[f64; 4]] {
        let n = self.shape.nbody as usize;
        // SAFETY: xquat holds 4*nbody reals.
        unsafe { std::slice::from_raw_parts(self.d().xquat as *const [f64; 4], n) }
    }
    /// Geom positions (world, m) and orientation matrices (row-major 3x3).
    pub fn geom_xpos(&self) -> &[[f64; 3]] {
        let n = self.shape.ngeom as usize;
        // SAFETY: geom_xpos holds 3*ngeom reals.
        unsafe { std::slice::from_raw_parts(self.d().geom_xpos as *const [f64; 3], n) }
    }

    /// Number of active contacts.
    pub fn ncon(&self) -> usize {
        self.d().ncon.max(0) as usize
    }

    /// The active contacts.
    pub fn contacts(&self) -> impl Iterator<Item = Contact> + '_ {
        let n = self.ncon();
        // SAFETY: `contact` holds at least ncon entries.
        let raw: &[ffi::mjContact] = if n == 0 {
            &[]
        } else {
            unsafe { std::slice::from_raw_parts(self.d().contact, n) }
        };
        raw.iter().enumerate().map(|(index, c)| Contact {
            index,
            geom1: c.geom1 as usize,
            geom2: c.geom2 as usize,
            dist_m: c.dist,
            pos_m: [c.pos[0], c.pos[1], c.pos[2]],
            normal: [c.frame[0], c.frame[1], c.frame[2]],
        })
    }

    /// Contact force of contact `index` in its contact frame: normal force
    /// first (N), then tangential; `mj_contactForce`.
    pub fn contact_force(&self, model: &Model, index: usize) -> Result<[f64; 6]> {
        self.check_model(model)?;
        if index >= self.ncon() {
            return Err(SimError::Invalid(format!(
                "contact {index} of {}",
                self.ncon()
            )));
        }
        let mut out = [0.0; 6];
        // SAFETY: matching model and data, index < ncon.
        unsafe { ffi::mj_contactForce(model.raw(), self.d(), index as i32, out.as_mut_ptr()) };
        check_error()?;
        Ok(out)
    }

    fn reals(&self, p: *mut f64, n: i32) -> &[f64] {
        if n <= 0 || p.is_null() {
            return &[];
        }
        // SAFETY: p is an mjData array of exactly n reals.
        unsafe { std::slice::from_raw_parts(p, n as usize) }
    }
    fn reals_mut(&mut self, p: *mut f64, n: i32) -> &mut [f64] {
        if n <= 0 || p.is_null() {
            return &mut [];
        }
        // SAFETY: as above, exclusive through &mut self.
        unsafe { std::slice::from_raw_parts_mut(p, n as usize) }
    }
}

/// Raw-FFI loops for benchmarks that compare our layer with bare `mj_step`.
/// Not part of the stable API; used by `benches/` only.
#[doc(hidden)]
pub mod raw_bench {
    use super::*;

    /// Where the PD law reads and writes, in raw array offsets.
    pub struct RawPd<'a> {
        pub qpos_adr: &'a [usize],
        pub dof_adr: &'a [usize],
        pub actuator: &'a [usize],
        pub target_rad: &'a [f64],
        pub kp: f64,
        pub kd: f64,
        pub limit_nm: &'a [f64],
    }

    /// `n` bare `mj_step` calls, each after the same PD law written straight
    /// into `d->ctrl` from `d->qpos`/`d->qvel` pointers: no checks, no slices.
    pub fn raw_pd_steps(model: &Model, data: &mut Data, n: usize, pd: &RawPd) {
        let d = data.ptr.as_ptr();
        for _ in 0..n {
            // SAFETY: data was made for model (constructor invariant); the
            // offsets come from the same model.
            unsafe {
                let (qpos, qvel, ctrl) = ((*d).qpos, (*d).qvel, (*d).ctrl);
                for i in 0..pd.actuator.len() {
                    let e = *qpos.add(pd.qpos_adr[i]);
                    let v = *qvel.add(pd.dof_adr[i]);
                    let tau = pd.kp * (pd.target_rad[i] - e) - pd.kd * v;
                    *ctrl.add(pd.actuator[i]) = tau.clamp(-pd.limit_nm[i], pd.limit_nm[i]);
                }
                ffi::mj_step(model.raw(), d);
            }
        }
    }

    /// `n` bare `mj_step` calls with whatever ctrl is set.
    pub fn raw_steps(model: &Model, data: &mut Data, n: usize) {
        for _ in 0..n {
            // SAFETY: data was made for model (constructor invariant).
            unsafe { ffi::mj_step(model.raw(), data.ptr.as_ptr()) };
        }
    }
}
