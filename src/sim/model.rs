//! [`Model`]: an owned, immutable-by-default `mjModel`.

use std::ffi::{c_char, CStr, CString};
use std::path::Path;
use std::ptr::NonNull;
use std::sync::atomic::{AtomicU64, Ordering};

use super::error::{install_handlers, Result, SimError};
use super::ffi;
use super::shim;

/// Source of model family ids: one per loaded model, shared by its clones.
static NEXT_FAMILY: AtomicU64 = AtomicU64::new(1);

/// MuJoCo object kinds used for name lookups.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ObjKind {
    Body,
    Joint,
    Geom,
    Site,
    Actuator,
    Key,
    Hfield,
}

impl ObjKind {
    fn raw(self) -> i32 {
        (match self {
            ObjKind::Body => ffi::mjtObj__mjOBJ_BODY,
            ObjKind::Joint => ffi::mjtObj__mjOBJ_JOINT,
            ObjKind::Geom => ffi::mjtObj__mjOBJ_GEOM,
            ObjKind::Site => ffi::mjtObj__mjOBJ_SITE,
            ObjKind::Actuator => ffi::mjtObj__mjOBJ_ACTUATOR,
            ObjKind::Key => ffi::mjtObj__mjOBJ_KEY,
            ObjKind::Hfield => ffi::mjtObj__mjOBJ_HFIELD,
        }) as i32
    }

    pub fn label(self) -> &'static str {
        match self {
            ObjKind::Body => "body",
            ObjKind::Joint => "joint",
            ObjKind::Geom => "geom",
            ObjKind::Site => "site",
            ObjKind::Actuator => "actuator",
            ObjKind::Key => "keyframe",
            ObjKind::Hfield => "heightfield",
        }
    }
}

/// Joint kinds (`mjtJoint`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JointKind {
    Free,
    Ball,
    Slide,
    Hinge,
}

/// Geom shapes (`mjtGeom`) that the robot and scenes use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GeomShape {
    Plane,
    Hfield,
    Sphere,
    Capsule,
    Ellipsoid,
    Cylinder,
    Box,
    Mesh,
}

/// An owned MuJoCo model. Freed on drop; `Send + Sync` because MuJoCo never
/// mutates a model during simulation and we only hand out `&mut` through `&mut self`.
///
/// Every loaded model gets a fresh *family* id; [`Model::try_clone`] keeps it.
/// The safe API only changes values (masses, friction, heights, time step),
/// never sizes, so all models of one family have the same layout and a
/// [`super::Data`] made for one of them may be stepped with any of them, and
/// with no other model (checked exactly on every call).
pub struct Model {
    ptr: NonNull<ffi::mjModel>,
    family: u64,
}

// SAFETY: an mjModel is a plain heap allocation with no thread affinity; shared
// access is read-only (mj_step takes `const mjModel*`).
unsafe impl Send for Model {}
// SAFETY: `&Model` only reads the mjModel (every writer takes `&mut Model`), and
// MuJoCo's readers of a `const mjModel*` do not mutate it.
unsafe impl Sync for Model {}

impl Drop for Model {
    fn drop(&mut self) {
        // SAFETY: we own the pointer, allocated by mj_loadXML or mj_copyModel.
        unsafe { ffi::mj_deleteModel(self.ptr.as_ptr()) }
    }
}

impl std::fmt::Debug for Model {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Model")
            .field("nq", &self.nq())
            .field("nv", &self.nv())
            .field("nu", &self.nu())
            .field("nbody", &self.nbody())
            .finish()
    }
}

const LOAD_ERROR_LEN: usize = 1024;

impl Model {
    /// Loads an MJCF file; includes and assets resolve relative to its folder.
    pub fn from_xml_path(path: impl AsRef<Path>) -> Result<Model> {
        let path = path.as_ref();
        if let Err(e) = std::fs::metadata(path) {
            return Err(SimError::ModelFile {
                path: path.to_path_buf(),
                reason: e.to_string(),
            });
        }
        let c_path =
            CString::new(path.to_string_lossy().as_bytes()).map_err(|_| SimError::ModelFile {
                path: path.to_path_buf(),
                reason: "path contains a NUL byte".into(),
            })?;
        load(&c_path, None, &path.display().to_string())
    }

    /// Loads a self-contained MJCF document from memory (through MuJoCo's VFS).
    /// `name` only labels error messages.
    pub fn from_xml_str(xml: &str, name: &str) -> Result<Model> {
        install_handlers();
        const VFS_NAME: &CStr = c"rall_model.xml";
        let vfs = Vfs::with_file(VFS_NAME, xml.as_bytes())?;
        load(VFS_NAME, Some(&vfs), name)
    }

    /// A deep copy (`mj_copyModel`) of the same family, e.g. one per worker
    /// thread for domain randomisation.
    pub fn try_clone(&self) -> Result<Model> {
        install_handlers();
        let mut raw = std::ptr::null_mut();
        // SAFETY: src is a valid model; the shim asks MuJoCo to allocate the copy.
        let rc = unsafe { shim::rall_mj_copyModel(self.ptr.as_ptr(), &mut raw) };
        shim::check(rc, "mj_copyModel")?;
        NonNull::new(raw)
            .map(|ptr| Model {
                ptr,
                family: self.family,
            })
            .ok_or_else(|| SimError::MuJoCo {
                call: "mj_copyModel",
                message: "returned no model".into(),
            })
    }

    /// This model's family id (see the type's documentation).
    pub fn family(&self) -> u64 {
        self.family
    }

    pub(crate) fn raw(&self) -> *const ffi::mjModel {
        self.ptr.as_ptr()
    }

    fn m(&self) -> &ffi::mjModel {
        // SAFETY: the pointer is valid for self's lifetime.
        unsafe { self.ptr.as_ref() }
    }

    fn m_mut(&mut self) -> &mut ffi::mjModel {
        // SAFETY: unique access through &mut self.
        unsafe { self.ptr.as_mut() }
    }

    pub fn nq(&self) -> usize {
        self.m().nq as usize
    }
    pub fn nv(&self) -> usize {
        self.m().nv as usize
    }
    pub fn nu(&self) -> usize {
        self.m().nu as usize
    }
    pub fn nbody(&self) -> usize {
        self.m().nbody as usize
    }
    pub fn njnt(&self) -> usize {
        self.m().njnt as usize
    }
    pub fn ngeom(&self) -> usize {
        self.m().ngeom as usize
    }
    pub fn nkey(&self) -> usize {
        self.m().nkey as usize
    }
    pub fn nhfield(&self) -> usize {
        self.m().nhfield as usize
    }

    /// Physics time step in seconds.
    pub fn timestep_s(&self) -> f64 {
        self.m().opt.timestep
    }
    pub fn set_timestep_s(&mut self, dt_s: f64) {
        self.m_mut().opt.timestep = dt_s;
    }
    /// Gravity vector (m/s^2, world frame).
    pub fn gravity(&self) -> [f64; 3] {
        self.m().opt.gravity
    }

    /// Sum of all body masses (kg).
    pub fn total_mass_kg(&self) -> f64 {
        // SAFETY: valid model.
        unsafe { ffi::mj_getTotalmass(self.raw()) }
    }

    /// Name -> id, `None` when absent.
    pub fn id(&self, kind: ObjKind, name: &str) -> Option<usize> {
        let c = CString::new(name).ok()?;
        // SAFETY: valid model and NUL-terminated name.
        let id = unsafe { ffi::mj_name2id(self.raw(), kind.raw(), c.as_ptr()) };
        (id >= 0).then_some(id as usize)
    }

    /// Name -> id, or an error naming what was looked for.
    pub fn require_id(&self, kind: ObjKind, name: &str) -> Result<usize> {
        self.id(kind, name).ok_or_else(|| SimError::UnknownName {
            kind: kind.label(),
            name: name.to_string(),
        })
    }

    /// Id -> name (empty string for unnamed objects).
    pub fn name(&self, kind: ObjKind, id: usize) -> &str {
        // SAFETY: valid model; MuJoCo returns null for out-of-range ids or a
        // pointer into the model's name buffer, alive as long as self.
        let p: *const c_char = unsafe { ffi::mj_id2name(self.raw(), kind.raw(), id as i32) };
        if p.is_null() {
            return "";
        }
        // SAFETY: p is non-null and points at a NUL-terminated name inside the
        // model's name buffer, which lives (unchanged) as long as &self.
        unsafe { CStr::from_ptr(p) }.to_str().unwrap_or("")
    }

    // --- bodies ---------------------------------------------------------
    pub fn body_parent(&self, body: usize) -> usize {
        self.ints(self.m().body_parentid, self.nbody())[body] as usize
    }
    /// Position of each body's frame in its parent's frame (m).
    pub fn body_pos_m(&self) -> &[[f64; 3]] {
        self.vec3s(self.m().body_pos, self.nbody())
    }
    /// Orientation of each body's frame in its parent's frame (w, x, y, z).
    pub fn body_quat(&self) -> &[[f64; 4]] {
        let n = self.nbody();
        let p = self.m().body_quat;
        if n == 0 || p.is_null() {
            return &[];
        }
        // SAFETY: body_quat holds 4*nbody reals.
        unsafe { std::slice::from_raw_parts(p as *const [f64; 4], n) }
    }
    /// Joints of each body (0: welded to its parent).
    pub fn body_joint_count(&self, body: usize) -> usize {
        self.ints(self.m().body_jntnum, self.nbody())[body] as usize
    }
    /// Body masses (kg), one per body.
    pub fn body_mass_kg(&self) -> &[f64] {
        self.reals(self.m().body_mass, self.nbody())
    }
    pub fn body_mass_kg_mut(&mut self) -> &mut [f64] {
        let n = self.nbody();
        self.reals_mut(self.m().body_mass, n)
    }
    /// Centre of mass of each body in its body frame (m).
    pub fn body_ipos_m(&self) -> &[[f64; 3]] {
        self.vec3s(self.m().body_ipos, self.nbody())
    }
    pub fn body_ipos_m_mut(&mut self) -> &mut [[f64; 3]] {
        let n = self.nbody();
        self.vec3s_mut(self.m().body_ipos, n)
    }
    /// Sets a body's mass (kg), keeping the subtree masses of it and its
    /// ancestors consistent (what `mj_setConst` would recompute). Inertia is kept.
    pub fn set_body_mass_kg(&mut self, body: usize, mass_kg: f64) {
        let n = self.nbody();
        let delta = mass_kg - self.body_mass_kg()[body];
        self.body_mass_kg_mut()[body] = mass_kg;
        let mut b = body;
        loop {
            let parent = self.body_parent(b);
            self.reals_mut(self.m().body_subtreemass, n)[b] += delta;
            if b == 0 {
                break;
            }
            b = parent;
        }
    }
    /// Mass of each body's subtree (kg).
    pub fn body_subtree_mass_kg(&self) -> &[f64] {
        self.reals(self.m().body_subtreemass, self.nbody())
    }
    /// Subtree masses, writable: keep them equal to the sums of
    /// [`Model::body_mass_kg`] over each subtree (MuJoCo reads both).
    pub fn body_subtree_mass_kg_mut(&mut self) -> &mut [f64] {
        let n = self.nbody();
        self.reals_mut(self.m().body_subtreemass, n)
    }
    /// Diagonal inertia in the body's inertial frame (kg m^2).
    pub fn body_inertia(&self) -> &[[f64; 3]] {
        self.vec3s(self.m().body_inertia, self.nbody())
    }
    pub fn body_inertia_mut(&mut self) -> &mut [[f64; 3]] {
        let n = self.nbody();
        self.vec3s_mut(self.m().body_inertia, n)
    }

    // --- joints ---------------------------------------------------------
    pub fn joint_kind(&self, joint: usize) -> JointKind {
        match self.ints(self.m().jnt_type, self.njnt())[joint] as u32 {
            ffi::mjtJoint__mjJNT_FREE => JointKind::Free,
            ffi::mjtJoint__mjJNT_BALL => JointKind::Ball,
            ffi::mjtJoint__mjJNT_SLIDE => JointKind::Slide,
            _ => JointKind::Hinge,
        }
    }
    pub fn joint_qpos_adr(&self, joint: usize) -> usize {
        self.ints(self.m().jnt_qposadr, self.njnt())[joint] as usize
    }
    pub fn joint_dof_adr(&self, joint: usize) -> usize {
        self.ints(self.m().jnt_dofadr, self.njnt())[joint] as usize
    }
    pub fn joint_body(&self, joint: usize) -> usize {
        self.ints(self.m().jnt_bodyid, self.njnt())[joint] as usize
    }
    /// Joint range (rad for hinges); `None` when the joint is unlimited.
    pub fn joint_range(&self, joint: usize) -> Option<[f64; 2]> {
        let limited = self.bytes(self.m().jnt_limited, self.njnt())[joint] != 0;
        limited.then(|| self.vec2s(self.m().jnt_range, self.njnt())[joint])
    }

    // --- actuators ------------------------------------------------------
    /// The joint an actuator drives (`None` for non-joint transmissions).
    pub fn actuator_joint(&self, act: usize) -> Option<usize> {
        let trntype = self.ints(self.m().actuator_trntype, self.nu())[act] as u32;
        let ids = self.ints(self.m().actuator_trnid, 2 * self.nu());
        (trntype == ffi::mjtTrn__mjTRN_JOINT).then_some(ids[2 * act] as usize)
    }
    /// Control range, `None` when unlimited.
    pub fn actuator_ctrl_range(&self, act: usize) -> Option<[f64; 2]> {
        let limited = self.bytes(self.m().actuator_ctrllimited, self.nu())[act] != 0;
        limited.then(|| self.vec2s(self.m().actuator_ctrlrange, self.nu())[act])
    }

    // --- geoms ----------------------------------------------------------
    pub fn geom_body(&self, geom: usize) -> usize {
        self.ints(self.m().geom_bodyid, self.ngeom())[geom] as usize
    }
    pub fn geom_shape(&self, geom: usize) -> GeomShape {
        match self.ints(self.m().geom_type, self.ngeom())[geom] as u32 {
            ffi::mjtGeom__mjGEOM_PLANE => GeomShape::Plane,
            ffi::mjtGeom__mjGEOM_HFIELD => GeomShape::Hfield,
            ffi::mjtGeom__mjGEOM_SPHERE => GeomShape::Sphere,
            ffi::mjtGeom__mjGEOM_CAPSULE => GeomShape::Capsule,
            ffi::mjtGeom__mjGEOM_ELLIPSOID => GeomShape::Ellipsoid,
            ffi::mjtGeom__mjGEOM_CYLINDER => GeomShape::Cylinder,
            ffi::mjtGeom__mjGEOM_BOX => GeomShape::Box,
            _ => GeomShape::Mesh,
        }
    }
    /// MuJoCo size parameters (meaning depends on the shape; half-sizes for boxes).
    pub fn geom_size(&self) -> &[[f64; 3]] {
        self.vec3s(self.m().geom_size, self.ngeom())
    }
    /// Geom position in its body frame (m).
    pub fn geom_pos(&self) -> &[[f64; 3]] {
        self.vec3s(self.m().geom_pos, self.ngeom())
    }
    /// Geom orientation in its body frame (unit quaternion, w x y z).
    pub fn geom_quat(&self) -> &[[f64; 4]] {
        let n = self.ngeom();
        let p = self.m().geom_quat;
        if n == 0 || p.is_null() {
            return &[];
        }
        // SAFETY: geom_quat holds 4*ngeom reals.
        unsafe { std::slice::from_raw_parts(p as *const [f64; 4], n) }
    }
    pub fn geom_rgba(&self) -> &[[f32; 4]] {
        let n = self.ngeom();
        let p = self.m().geom_rgba;
        if n == 0 || p.is_null() {
            return &[];
        }
        // SAFETY: geom_rgba holds 4*ngeom floats.
        unsafe { std::slice::from_raw_parts(p as *const [f32; 4], n) }
    }
    /// Sliding, torsional, rolling friction per geom.
    pub fn geom_friction(&self) -> &[[f64; 3]] {
        self.vec3s(self.m().geom_friction, self.ngeom())
    }
    pub fn geom_friction_mut(&mut self) -> &mut [[f64; 3]] {
        let n = self.ngeom();
        self.vec3s_mut(self.m().geom_friction, n)
    }
    /// Collision bits (contype, conaffinity).
    pub fn geom_collision_bits(&self, geom: usize) -> (i32, i32) {
        let n = self.ngeom();
        (
            self.ints(self.m().geom_contype, n)[geom],
            self.ints(self.m().geom_conaffinity, n)[geom],
        )
    }
    /// The heightfield a geom uses, if it is an hfield geom.
    pub fn geom_hfield(&self, geom: usize) -> Option<usize> {
        let id = self.ints(self.m().geom_dataid, self.ngeom())[geom];
        (self.geom_shape(geom) == GeomShape::Hfield && id >= 0).then_some(id as usize)
    }

    // --- heightfields ---------------------------------------------------
    /// (rows, columns) of heightfield `h`.
    pub fn hfield_shape(&self, h: usize) -> (usize, usize) {
        let n = self.nhfield();
        let rows = self.ints(self.m().hfield_nrow, n)[h] as usize;
        let cols = self.ints(self.m().hfield_ncol, n)[h] as usize;
        (rows, cols)
    }
    /// (radius_x, radius_y, elevation_z, base_z) in metres.
    pub fn hfield_size(&self, h: usize) -> [f64; 4] {
        let n = self.nhfield();
        let p = self.m().hfield_size;
        let all: &[[f64; 4]] = if n == 0 || p.is_null() {
            &[]
        } else {
            // SAFETY: hfield_size holds 4*nhfield reals.
            unsafe { std::slice::from_raw_parts(p as *const [f64; 4], n) }
        };
        all[h]
    }
    /// Row-major elevation samples of heightfield `h`, each in [0, 1] of `elevation_z`.
    pub fn hfield_data_mut(&mut self, h: usize) -> &mut [f32] {
        let range = self.hfield_range(h);
        let n = self.m().nhfielddata.max(0) as usize;
        let p = self.m().hfield_data;
        let all: &mut [f32] = if n == 0 || p.is_null() {
            &mut []
        } else {
            // SAFETY: hfield_data holds nhfielddata floats, unique through &mut self.
            unsafe { std::slice::from_raw_parts_mut(p, n) }
        };
        &mut all[range]
    }
    pub fn hfield_data(&self, h: usize) -> &[f32] {
        let range = self.hfield_range(h);
        let n = self.m().nhfielddata.max(0) as usize;
        let p = self.m().hfield_data;
        let all: &[f32] = if n == 0 || p.is_null() {
            &[]
        } else {
            // SAFETY: hfield_data holds nhfielddata floats.
            unsafe { std::slice::from_raw_parts(p, n) }
        };
        &all[range]
    }
    /// Heightfield `h`'s block in `hfield_data` (indexing checked by the caller's slice).
    fn hfield_range(&self, h: usize) -> std::ops::Range<usize> {
        let (rows, cols) = self.hfield_shape(h);
        let adr = self.ints(self.m().hfield_adr, self.nhfield())[h].max(0) as usize;
        adr..adr + rows * cols
    }

    // --- keyframes ------------------------------------------------------
    /// qpos of keyframe `key`.
    pub fn key_qpos(&self, key: usize) -> &[f64] {
        let nq = self.nq();
        &self.reals(self.m().key_qpos, self.nkey() * nq)[key * nq..(key + 1) * nq]
    }

    // --- raw slice helpers (the only place model arrays become slices) ----
    fn reals(&self, p: *mut f64, n: usize) -> &[f64] {
        if n == 0 || p.is_null() {
            return &[];
        }
        // SAFETY: callers pass a model array and its exact length.
        unsafe { std::slice::from_raw_parts(p, n) }
    }
    fn reals_mut(&mut self, p: *mut f64, n: usize) -> &mut [f64] {
        if n == 0 || p.is_null() {
            return &mut [];
        }
        // SAFETY: as above, unique through &mut self.
        unsafe { std::slice::from_raw_parts_mut(p, n) }
    }
    fn ints(&self, p: *mut i32, n: usize) -> &[i32] {
        if n == 0 || p.is_null() {
            return &[];
        }
        // SAFETY: callers pass a model array and its exact length.
        unsafe { std::slice::from_raw_parts(p, n) }
    }
    fn bytes(&self, p: *mut u8, n: usize) -> &[u8] {
        if n == 0 || p.is_null() {
            return &[];
        }
        // SAFETY: callers pass a model array and its exact length.
        unsafe { std::slice::from_raw_parts(p, n) }
    }
    fn vec2s(&self, p: *mut f64, n: usize) -> &[[f64; 2]] {
        if n == 0 || p.is_null() {
            return &[];
        }
        // SAFETY: array of 2*n reals.
        unsafe { std::slice::from_raw_parts(p as *const [f64; 2], n) }
    }
    fn vec3s(&self, p: *mut f64, n: usize) -> &[[f64; 3]] {
        if n == 0 || p.is_null() {
            return &[];
        }
        // SAFETY: array of 3*n reals.
        unsafe { std::slice::from_raw_parts(p as *const [f64; 3], n) }
    }
    fn vec3s_mut(&mut self, p: *mut f64, n: usize) -> &mut [[f64; 3]] {
        if n == 0 || p.is_null() {
            return &mut [];
        }
        // SAFETY: array of 3*n reals, unique through &mut self.
        unsafe { std::slice::from_raw_parts_mut(p as *mut [f64; 3], n) }
    }
}

/// Loads through `mj_loadXML`, turning MuJoCo's error buffer into a [`SimError`].
fn load(file: &CStr, vfs: Option<&Vfs>, name: &str) -> Result<Model> {
    install_handlers();
    let mut err = [0 as c_char; LOAD_ERROR_LEN];
    let vfs_ptr = vfs.map_or(std::ptr::null(), |v| v.raw());
    let mut raw = std::ptr::null_mut();
    // SAFETY: valid C strings and an error buffer of the declared length.
    let rc = unsafe {
        shim::rall_mj_loadXML(
            file.as_ptr(),
            vfs_ptr,
            err.as_mut_ptr(),
            LOAD_ERROR_LEN as i32,
            &mut raw,
        )
    };
    if rc != 0 {
        // MuJoCo raised an error through its handler (left via the shim); the
        // partial model, if any, is lost rather than trusted.
        return Err(SimError::Load {
            source_name: name.into(),
            message: shim::last_error(),
        });
    }
    // SAFETY: the buffer was zeroed and MuJoCo writes at most LOAD_ERROR_LEN - 1
    // characters; the last byte stays NUL.
    err[LOAD_ERROR_LEN - 1] = 0;
    // SAFETY: `err` is a live local buffer ending in the NUL just written.
    let message = unsafe { CStr::from_ptr(err.as_ptr()) }
        .to_string_lossy()
        .trim()
        .to_string();
    match NonNull::new(raw) {
        Some(ptr) => Ok(Model {
            ptr,
            family: NEXT_FAMILY.fetch_add(1, Ordering::Relaxed),
        }),
        None => Err(SimError::Load {
            source_name: name.into(),
            message: if message.is_empty() {
                "unknown error".into()
            } else {
                message
            },
        }),
    }
}

/// MuJoCo's virtual file system (about 2 MB: kept on the heap).
struct Vfs {
    raw: Box<ffi::mjVFS>,
}

impl Vfs {
    fn with_file(name: &CStr, content: &[u8]) -> Result<Vfs> {
        // SAFETY: mjVFS is plain old data; zeroed is a valid start, then defaulted.
        let mut raw: Box<ffi::mjVFS> = unsafe { Box::new(std::mem::zeroed()) };
        // SAFETY: `raw` is a live, exclusively owned mjVFS; mj_defaultVFS only
        // initialises its fields.
        unsafe { ffi::mj_defaultVFS(&mut *raw) };
        let size = i32::try_from(content.len())
            .map_err(|_| SimError::Invalid("MJCF text larger than 2 GiB".into()))?;
        // SAFETY: valid VFS and name; MuJoCo allocates `size` bytes.
        let rc = unsafe { ffi::mj_makeEmptyFileVFS(&mut *raw, name.as_ptr(), size) };
        if rc != 0 {
            return Err(SimError::Invalid(format!(
                "MuJoCo VFS refused the file (code {rc})"
            )));
        }
        // SAFETY: valid, initialised VFS and a NUL-terminated name; read-only lookup.
        let index = unsafe { ffi::mj_findFileVFS(&*raw, name.as_ptr()) };
        if index < 0 {
            return Err(SimError::Invalid("MuJoCo VFS lost the file".into()));
        }
        // SAFETY: filedata[index] has `size` bytes allocated by mj_makeEmptyFileVFS.
        unsafe {
            std::ptr::copy_nonoverlapping(
                content.as_ptr(),
                raw.filedata[index as usize] as *mut u8,
                content.len(),
            )
        };
        Ok(Vfs { raw })
    }

    fn raw(&self) -> *const ffi::mjVFS {
        &*self.raw
    }
}

impl Drop for Vfs {
    fn drop(&mut self) {
        // SAFETY: frees the buffers MuJoCo allocated in this VFS.
        unsafe { ffi::mj_deleteVFS(&mut *self.raw) }
    }
}
