//! [`Data`]: the simulation state of one model (`mjData`).

use std::ptr::NonNull;

use super::error::{install_handlers, Result, SimError};
use super::ffi;
use super::model::{Model, ObjKind};
use super::shim;

/// The system's page size in bytes.
fn page_size() -> usize {
    static PAGE: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *PAGE.get_or_init(|| {
        // SAFETY: sysconf has no preconditions.
        let n = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
        if n > 0 {
            n as usize
        } else {
            4096
        }
    })
}

/// The array sizes of the model family a `Data` was made for (slices use them).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Shape {
    nq: i32,
    nv: i32,
    nu: i32,
    nbody: i32,
    ngeom: i32,
    na: i32,
    nmocap: i32,
    /// Arena capacities (`<size>`), for [`Data::arena_use`].
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
            nbody: m.nbody,
            ngeom: m.ngeom,
            na: m.na,
            nmocap: m.nmocap,
            nconmax: m.nconmax,
            njmax: m.njmax,
        }
    }
}

/// How much of MuJoCo's preallocated arena a `Data` has used at most since its
/// last reset, beside its capacity (`<size nconmax njmax nstack>`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ArenaUse {
    pub contacts: usize,
    pub contacts_max: usize,
    pub constraints: usize,
    pub constraints_max: usize,
    /// In mjtNums.
    pub stack: usize,
    pub stack_max: usize,
}

impl ArenaUse {
    /// Element-wise maximum.
    pub fn max(self, other: ArenaUse) -> ArenaUse {
        ArenaUse {
            contacts: self.contacts.max(other.contacts),
            contacts_max: self.contacts_max.max(other.contacts_max),
            constraints: self.constraints.max(other.constraints),
            constraints_max: self.constraints_max.max(other.constraints_max),
            stack: self.stack.max(other.stack),
            stack_max: self.stack_max.max(other.stack_max),
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
///
/// Tied to the model family it was made for: every call that takes a model
/// refuses one of another family ([`SimError::ModelMismatch`]).
pub struct Data {
    ptr: NonNull<ffi::mjData>,
    family: u64,
    shape: Shape,
    warnings_seen: Warnings,
    /// Set when a MuJoCo error interrupted a call (the state is undefined);
    /// cleared by a reset.
    broken: Option<String>,
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
        install_handlers();
        let mut raw = std::ptr::null_mut();
        // SAFETY: valid model; the shim returns 1 (and no data) on a MuJoCo error.
        let rc = unsafe { shim::rall_mj_makeData(model.raw(), &mut raw) };
        shim::check(rc, "mj_makeData")?;
        let ptr = NonNull::new(raw).ok_or_else(|| SimError::MuJoCo {
            call: "mj_makeData",
            message: "returned no data".into(),
        })?;
        let mut data = Data {
            ptr,
            family: model.family(),
            shape: Shape::of(model),
            warnings_seen: Warnings::default(),
            broken: None,
        };
        // The model's reference pose (qpos0) may be no real state (legs through
        // the ground, more contacts than the arena holds): its warnings are not
        // the caller's concern, MuJoCo errors are. Resets start counting afresh.
        let r = match data.forward(model) {
            Ok(()) | Err(SimError::Unstable { .. }) => Ok(()),
            Err(e) => Err(e),
        };
        data.release_zero_pages();
        r.map(|()| data)
    }

    /// The addresses of the whole pages inside the data's buffer.
    fn buffer_whole_pages(&self) -> std::ops::Range<usize> {
        let page = page_size();
        let d = self.d();
        let (start, len) = (d.buffer as usize, d.nbuffer.max(0) as usize);
        start.next_multiple_of(page)..(start + len) / page * page
    }

    /// Hands the all-zero pages of the data's buffer back to the kernel
    /// (`madvise(MADV_DONTNEED)`), so that an env's resident memory is what its
    /// physics uses, not what the arena could hold.
    ///
    /// MuJoCo 2.2 sizes every mjData for `njmax` constraint rows (a dense
    /// njmax x njmax matrix among its arrays: 1.2 MB at njmax 300) and
    /// `mj_resetData` zero-fills the whole buffer, which makes every page resident,
    /// while a walking robot uses a few dozen rows. A private anonymous page given
    /// back this way reads as zeros again, so the contents, and the physics, are
    /// unchanged; only pages MuJoCo writes later come back.
    fn release_zero_pages(&mut self) {
        let page = page_size();
        let std::ops::Range { start: first, end } = self.buffer_whole_pages();
        let mut run: Option<usize> = None;
        let give_back = |from: usize, to: usize| {
            // SAFETY: [from, to) is whole pages inside the buffer this Data owns
            // (allocated by mj_makeData, private anonymous memory), all zero.
            unsafe { libc::madvise(from as *mut libc::c_void, to - from, libc::MADV_DONTNEED) };
        };
        let mut p = first;
        while p < end {
            // SAFETY: the page lies inside the buffer (see above), aligned for u64.
            let words = unsafe { std::slice::from_raw_parts(p as *const u64, page / 8) };
            let zero = words.iter().all(|&w| w == 0);
            match (zero, run) {
                (true, None) => run = Some(p),
                (false, Some(from)) => {
                    give_back(from, p);
                    run = None;
                }
                _ => {}
            }
            p += page;
        }
        if let Some(from) = run {
            give_back(from, end);
        }
    }

    /// The family id of the model this data was made for.
    pub fn family(&self) -> u64 {
        self.family
    }

    #[inline]
    fn check_model(&self, model: &Model) -> Result<()> {
        if model.family() == self.family {
            Ok(())
        } else {
            Err(SimError::ModelMismatch(format!(
                "data of model family {} used with model family {}",
                self.family,
                model.family()
            )))
        }
    }

    /// Like [`Data::check_model`], and refuses a data left undefined by an error.
    #[inline]
    fn check_usable(&self, model: &Model) -> Result<()> {
        self.check_model(model)?;
        match &self.broken {
            None => Ok(()),
            Some(e) => Err(SimError::NeedsReset(e.clone())),
        }
    }

    /// Records a guarded call's failure: the data is unusable until a reset.
    fn guarded(&mut self, rc: std::ffi::c_int, call: &'static str) -> Result<()> {
        let r = shim::check(rc, call);
        if let Err(e) = &r {
            self.broken = Some(e.to_string());
        }
        r
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
        self.check_usable(model)?;
        // SAFETY: the data was made for this model's family (same layout).
        let rc = unsafe { shim::rall_mj_step(model.raw(), self.ptr.as_ptr()) };
        self.guarded(rc, "mj_step")?;
        self.after_call()
    }

    /// Recomputes derived quantities (kinematics, contacts, forces) without integrating.
    pub fn forward(&mut self, model: &Model) -> Result<()> {
        self.check_usable(model)?;
        // SAFETY: as in step.
        let rc = unsafe { shim::rall_mj_forward(model.raw(), self.ptr.as_ptr()) };
        self.guarded(rc, "mj_forward")?;
        self.after_call()
    }

    #[inline]
    fn after_call(&mut self) -> Result<()> {
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
    /// Also makes a data usable again after a MuJoCo error.
    pub fn reset(&mut self, model: &Model) -> Result<()> {
        self.check_model(model)?;
        // SAFETY: matching model family; mj_resetData also empties the stack.
        let rc = unsafe { shim::rall_mj_resetData(model.raw(), self.ptr.as_ptr()) };
        self.guarded(rc, "mj_resetData")?;
        self.broken = None;
        self.warnings_seen = Warnings::default();
        let r = self.forward(model);
        self.release_zero_pages();
        r
    }

    /// Resets to the keyframe called `name`.
    pub fn reset_to_keyframe(&mut self, model: &Model, name: &str) -> Result<()> {
        self.check_model(model)?;
        let key = model.require_id(ObjKind::Key, name)?;
        // SAFETY: matching model family, key id in range.
        let rc =
            unsafe { shim::rall_mj_resetDataKeyframe(model.raw(), self.ptr.as_ptr(), key as i32) };
        self.guarded(rc, "mj_resetDataKeyframe")?;
        self.broken = None;
        self.warnings_seen = Warnings::default();
        let r = self.forward(model);
        self.release_zero_pages();
        r
    }

    /// Arena use since the last reset, beside the capacities.
    pub fn arena_use(&self) -> ArenaUse {
        let d = self.d();
        ArenaUse {
            contacts: d.maxuse_con.max(0) as usize,
            contacts_max: self.shape.nconmax.max(0) as usize,
            constraints: d.maxuse_efc.max(0) as usize,
            constraints_max: self.shape.njmax.max(0) as usize,
            stack: d.maxuse_stack.max(0) as usize,
            stack_max: d.nstack.max(0) as usize,
        }
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
        self.d().ncon.clamp(0, self.shape.nconmax.max(0)) as usize
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
        self.check_usable(model)?;
        if index >= self.ncon() {
            return Err(SimError::Invalid(format!(
                "contact {index} of {}",
                self.ncon()
            )));
        }
        let mut out = [0.0; 6];
        // SAFETY: matching model family, index < ncon, 6 output reals.
        let rc = unsafe {
            shim::rall_mj_contactForce(model.raw(), self.d(), index as i32, out.as_mut_ptr())
        };
        shim::check(rc, "mj_contactForce")?;
        Ok(out)
    }

    /// The arrays `mj_step` reads besides the model, in a fixed order: time,
    /// qpos, qvel, act, ctrl, qacc_warmstart (the constraint solver's starting
    /// point), qfrc_applied, xfrc_applied, mocap_pos, mocap_quat. Everything else
    /// in mjData is recomputed from these by the next step, so restoring them
    /// ([`Data::set_physics_state`]) continues the simulation bit for bit.
    pub fn physics_state(&self) -> Vec<f64> {
        let d = self.d();
        let mut out = vec![d.time];
        for (p, n) in self.state_arrays() {
            out.extend_from_slice(self.reals(p, n));
        }
        out
    }

    /// Restores [`Data::physics_state`] (same model family, same length).
    pub fn set_physics_state(&mut self, model: &Model, state: &[f64]) -> Result<()> {
        self.check_model(model)?;
        let arrays = self.state_arrays();
        let len = 1 + arrays
            .iter()
            .map(|&(_, n)| n.max(0) as usize)
            .sum::<usize>();
        if state.len() != len {
            return Err(SimError::Invalid(format!(
                "a physics state of {} values for a model whose state has {len}",
                state.len()
            )));
        }
        self.set_time_s(state[0]);
        let mut at = 1;
        for (p, n) in arrays {
            let dst = self.reals_mut(p, n);
            dst.copy_from_slice(&state[at..at + dst.len()]);
            at += dst.len();
        }
        self.broken = None;
        Ok(())
    }

    /// Pointers and lengths of the arrays of [`Data::physics_state`].
    fn state_arrays(&self) -> [(*mut f64, i32); 9] {
        let (d, s) = (self.d(), &self.shape);
        [
            (d.qpos, s.nq),
            (d.qvel, s.nv),
            (d.act, s.na),
            (d.ctrl, s.nu),
            (d.qacc_warmstart, s.nv),
            (d.qfrc_applied, s.nv),
            (d.xfrc_applied, 6 * s.nbody),
            (d.mocap_pos, 3 * s.nmocap),
            (d.mocap_quat, 4 * s.nmocap),
        ]
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

    impl RawPd<'_> {
        /// Every offset inside its array and every list as long as the actuators:
        /// what makes the unchecked loop below sound.
        fn check(&self, data: &Data) -> Result<()> {
            let n = self.actuator.len();
            let s = data.shape;
            let lens_ok = [
                self.qpos_adr.len(),
                self.dof_adr.len(),
                self.target_rad.len(),
                self.limit_nm.len(),
            ]
            .iter()
            .all(|&l| l == n);
            let inside = |adr: &[usize], len: i32| adr.iter().all(|&a| a < len.max(0) as usize);
            if lens_ok
                && inside(self.qpos_adr, s.nq)
                && inside(self.dof_adr, s.nv)
                && inside(self.actuator, s.nu)
            {
                Ok(())
            } else {
                Err(SimError::Invalid(format!(
                    "raw PD offsets do not fit the data (nq {}, nv {}, nu {}) or differ in length",
                    s.nq, s.nv, s.nu
                )))
            }
        }
    }

    /// `n` bare `mj_step` calls, each after the same PD law written straight
    /// into `d->ctrl` from `d->qpos`/`d->qvel` pointers: offsets checked once,
    /// then no checks, no slices, no warning scan.
    pub fn raw_pd_steps(model: &Model, data: &mut Data, n: usize, pd: &RawPd) -> Result<()> {
        data.check_usable(model)?;
        pd.check(data)?;
        let d = data.ptr.as_ptr();
        for _ in 0..n {
            // SAFETY: data belongs to model's family; every offset was checked
            // against the array sizes above.
            let rc = unsafe {
                let (qpos, qvel, ctrl) = ((*d).qpos, (*d).qvel, (*d).ctrl);
                for i in 0..pd.actuator.len() {
                    let e = *qpos.add(pd.qpos_adr[i]);
                    let v = *qvel.add(pd.dof_adr[i]);
                    let tau = pd.kp * (pd.target_rad[i] - e) - pd.kd * v;
                    *ctrl.add(pd.actuator[i]) = tau.clamp(-pd.limit_nm[i], pd.limit_nm[i]);
                }
                shim::rall_mj_step(model.raw(), d)
            };
            data.guarded(rc, "mj_step")?;
        }
        Ok(())
    }

    /// `n` bare `mj_step` calls with whatever ctrl is set.
    pub fn raw_steps(model: &Model, data: &mut Data, n: usize) -> Result<()> {
        data.check_usable(model)?;
        for _ in 0..n {
            // SAFETY: data belongs to model's family (checked above).
            let rc = unsafe { shim::rall_mj_step(model.raw(), data.ptr.as_ptr()) };
            data.guarded(rc, "mj_step")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn aliengo() -> Model {
        Model::from_xml_path(concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml")).unwrap()
    }

    /// A deterministic, contact-rich control sequence (torques in N m).
    fn ctrl_at(step: usize, j: usize) -> f64 {
        30.0 * ((step as f64) * 0.07 + j as f64).sin()
    }

    fn buffer_pages(d: &Data) -> usize {
        d.buffer_whole_pages().len() / page_size()
    }

    fn resident_pages(d: &Data) -> usize {
        let pages = d.buffer_whole_pages();
        let mut v = vec![0u8; buffer_pages(d)];
        // SAFETY: page-aligned range inside the buffer; v has one byte per page.
        let rc = unsafe {
            libc::mincore(
                pages.start as *mut libc::c_void,
                pages.len(),
                v.as_mut_ptr(),
            )
        };
        assert_eq!(rc, 0, "mincore");
        v.iter().filter(|&&b| b & 1 == 1).count()
    }

    fn buffer_bytes(d: &Data) -> Vec<u8> {
        // SAFETY: the buffer is nbuffer bytes owned by d.
        unsafe { std::slice::from_raw_parts(d.d().buffer as *const u8, d.d().nbuffer as usize) }
            .to_vec()
    }

    #[test]
    fn released_pages_keep_the_contents_and_leave_memory() {
        let m = aliengo();
        let mut d = Data::new(&m).unwrap();
        let pages = buffer_pages(&d);
        for step in 0..200 {
            for j in 0..m.nu() {
                d.ctrl_mut()[j] = ctrl_at(step, j);
            }
            let _ = d.step(&m);
        }
        let before = buffer_bytes(&d);
        d.release_zero_pages();
        assert_eq!(buffer_bytes(&d), before, "the contents changed");
        d.reset(&m).unwrap();
        let resident = resident_pages(&d);
        println!("resident after a reset: {resident} of {pages} pages");
        assert!(
            resident * 4 < pages,
            "{resident} of {pages} pages resident after a reset"
        );
    }

    #[test]
    fn released_pages_leave_the_trajectory_bit_identical() {
        let m = aliengo();
        let mut plain = Data::new(&m).unwrap();
        let mut released = Data::new(&m).unwrap();
        for episode in 0..2 {
            plain.reset(&m).unwrap();
            released.reset(&m).unwrap();
            for step in 0..300 {
                for j in 0..m.nu() {
                    let u = ctrl_at(step + 1000 * episode, j);
                    plain.ctrl_mut()[j] = u;
                    released.ctrl_mut()[j] = u;
                }
                let a = plain.step(&m).is_ok();
                // Every step, the zero pages go back, so that MuJoCo meets fresh
                // zero pages wherever it reads before writing.
                released.release_zero_pages();
                let b = released.step(&m).is_ok();
                assert_eq!(a, b, "episode {episode} step {step}");
                let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(plain.qpos()), bits(released.qpos()), "qpos at {step}");
                assert_eq!(bits(plain.qvel()), bits(released.qvel()), "qvel at {step}");
                if !a {
                    break;
                }
            }
        }
    }
}
