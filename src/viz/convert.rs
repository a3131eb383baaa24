//! MuJoCo -> rerun conventions as pure functions (no rerun types, testable alone).
//!
//! - Quaternions: MuJoCo stores `w x y z`, rerun takes `x y z w`.
//! - Boxes: MuJoCo `size` = half-sizes, centred at `pos`, rotated by `quat`; rerun's
//!   `Boxes3D` takes the same (centre, half-size, rotation), so only the quaternion changes.
//! - Capsules: MuJoCo `size` = (radius, half-length), centred at `pos`, axis = local z.
//!   rerun's `Capsules3D` starts at one end: the end-cap centres are at `(0, 0, 0)` and
//!   `(0, 0, length)` before its translation and rotation. So `length = 2 h` and the
//!   translation is the lower end `pos - R(quat) (0, 0, h)`.
//! - Spheres / ellipsoids: centred, radii = `size` (sphere: `size[0]`).
//! - Cylinders: MuJoCo (radius, half-length), centred; rerun's `Cylinders3D` is centred
//!   too with the full length.
//! - Heightfields: a triangle mesh over the terrain samples (see [`heightfield_mesh`]).

use crate::sim::GeomShape;

/// MuJoCo `w x y z` to rerun `x y z w`, as f32.
pub fn quat_wxyz_to_xyzw(q: [f64; 4]) -> [f32; 4] {
    [q[1] as f32, q[2] as f32, q[3] as f32, q[0] as f32]
}

/// Rotates `v` by the unit quaternion `q` (`w x y z`).
pub fn rotate_wxyz(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let [w, x, y, z] = q;
    // v' = v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z)
    let u = [x, y, z];
    let c1 = cross(u, v);
    let c2 = cross(u, c1);
    [
        v[0] + 2.0 * (w * c1[0] + c2[0]),
        v[1] + 2.0 * (w * c1[1] + c2[1]),
        v[2] + 2.0 * (w * c1[2] + c2[2]),
    ]
}

/// Rotates `v` by the unit quaternion `q` (`x y z w`, rerun's order).
pub fn rotate_xyzw(q: [f32; 4], v: [f32; 3]) -> [f32; 3] {
    let r = rotate_wxyz(
        [q[3] as f64, q[0] as f64, q[1] as f64, q[2] as f64],
        [v[0] as f64, v[1] as f64, v[2] as f64],
    );
    [r[0] as f32, r[1] as f32, r[2] as f32]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn f32x3(v: [f64; 3]) -> [f32; 3] {
    [v[0] as f32, v[1] as f32, v[2] as f32]
}

/// A box in rerun's terms (`Boxes3D`: centre, half-size, rotation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxPrim {
    pub center: [f32; 3],
    pub half_size: [f32; 3],
    pub quat_xyzw: [f32; 4],
}

impl BoxPrim {
    /// The 8 corners as rerun draws them: `center + R (+-hx, +-hy, +-hz)`.
    pub fn corners(&self) -> [[f32; 3]; 8] {
        let mut out = [[0.0; 3]; 8];
        for (i, c) in out.iter_mut().enumerate() {
            let s = |bit: usize| if i >> bit & 1 == 1 { 1.0 } else { -1.0 };
            let local = [
                s(0) * self.half_size[0],
                s(1) * self.half_size[1],
                s(2) * self.half_size[2],
            ];
            let r = rotate_xyzw(self.quat_xyzw, local);
            *c = [
                self.center[0] + r[0],
                self.center[1] + r[1],
                self.center[2] + r[2],
            ];
        }
        out
    }
}

/// A capsule in rerun's terms (`Capsules3D`: length, radius, translation of the
/// first end-cap centre, rotation taking +z to the axis).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CapsulePrim {
    pub length: f32,
    pub radius: f32,
    pub translation: [f32; 3],
    pub quat_xyzw: [f32; 4],
}

impl CapsulePrim {
    /// End-cap centres as rerun draws them: `T + R (0, 0, 0)` and `T + R (0, 0, length)`.
    pub fn endpoints(&self) -> ([f32; 3], [f32; 3]) {
        let a = self.translation;
        let d = rotate_xyzw(self.quat_xyzw, [0.0, 0.0, self.length]);
        (a, [a[0] + d[0], a[1] + d[1], a[2] + d[2]])
    }
}

/// An ellipsoid (spheres included) in rerun's terms (`Ellipsoids3D`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EllipsoidPrim {
    pub center: [f32; 3],
    pub half_size: [f32; 3],
    pub quat_xyzw: [f32; 4],
}

/// A cylinder in rerun's terms (`Cylinders3D`: centred, full length).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CylinderPrim {
    pub center: [f32; 3],
    pub length: f32,
    pub radius: f32,
    pub quat_xyzw: [f32; 4],
}

/// One MuJoCo geom as a rerun primitive, in its body's frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Primitive {
    Box(BoxPrim),
    Capsule(CapsulePrim),
    Ellipsoid(EllipsoidPrim),
    Cylinder(CylinderPrim),
}

/// MuJoCo box (`size` = half-sizes) at `pos`, `quat` (w x y z).
pub fn box_from_mujoco(size: [f64; 3], pos: [f64; 3], quat: [f64; 4]) -> BoxPrim {
    BoxPrim {
        center: f32x3(pos),
        half_size: f32x3(size),
        quat_xyzw: quat_wxyz_to_xyzw(quat),
    }
}

/// MuJoCo capsule (`size[0]` radius, `size[1]` half-length along local z) centred at `pos`.
pub fn capsule_from_mujoco(size: [f64; 3], pos: [f64; 3], quat: [f64; 4]) -> CapsulePrim {
    let (radius, half) = (size[0], size[1]);
    let axis = rotate_wxyz(quat, [0.0, 0.0, half]);
    CapsulePrim {
        length: (2.0 * half) as f32,
        radius: radius as f32,
        translation: f32x3([pos[0] - axis[0], pos[1] - axis[1], pos[2] - axis[2]]),
        quat_xyzw: quat_wxyz_to_xyzw(quat),
    }
}

/// The rerun primitive of a geom (`size`, `pos`, `quat` from the model, body frame);
/// `None` for planes, heightfields and meshes (the ground is logged separately).
pub fn geom_primitive(
    shape: GeomShape,
    size: [f64; 3],
    pos: [f64; 3],
    quat: [f64; 4],
) -> Option<Primitive> {
    let q = quat_wxyz_to_xyzw(quat);
    match shape {
        GeomShape::Box => Some(Primitive::Box(box_from_mujoco(size, pos, quat))),
        GeomShape::Capsule => Some(Primitive::Capsule(capsule_from_mujoco(size, pos, quat))),
        GeomShape::Sphere => {
            let r = size[0] as f32;
            Some(Primitive::Ellipsoid(EllipsoidPrim {
                center: f32x3(pos),
                half_size: [r; 3],
                quat_xyzw: q,
            }))
        }
        GeomShape::Ellipsoid => Some(Primitive::Ellipsoid(EllipsoidPrim {
            center: f32x3(pos),
            half_size: f32x3(size),
            quat_xyzw: q,
        })),
        GeomShape::Cylinder => Some(Primitive::Cylinder(CylinderPrim {
            center: f32x3(pos),
            length: (2.0 * size[1]) as f32,
            radius: size[0] as f32,
            quat_xyzw: q,
        })),
        GeomShape::Plane | GeomShape::Hfield | GeomShape::Mesh => None,
    }
}

/// A triangle mesh (world frame) with per-vertex normals and colours.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriMesh {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    pub colors: Vec<[u8; 4]>,
    pub triangles: Vec<[u32; 3]>,
}

/// Ground colour ramp: low = dark brown, high = light sand.
fn height_color(t: f32) -> [u8; 4] {
    let t = t.clamp(0.0, 1.0);
    let lerp = |a: f32, b: f32| (a + (b - a) * t).round() as u8;
    [lerp(95.0, 215.0), lerp(80.0, 200.0), lerp(65.0, 165.0), 255]
}

/// A mesh over heightfield samples `ix in ix0..=ix1`, `iy in iy0..=iy1` of a
/// row-major grid (`heights[iy * nx + ix]` at world `(x0 + ix h, y0 + iy h)`,
/// the layout of `Terrain::heights_m`). Two triangles per cell, counter-clockwise
/// seen from above (normals point up). Colours ramp over `z_range`.
#[allow(clippy::too_many_arguments)]
pub fn heightfield_mesh(
    heights: &[f32],
    nx: usize,
    origin: [f64; 2],
    h: f64,
    (ix0, ix1): (usize, usize),
    (iy0, iy1): (usize, usize),
    z_range: (f64, f64),
) -> TriMesh {
    assert!(
        ix0 < ix1 && iy0 < iy1,
        "a heightfield mesh needs at least one cell"
    );
    assert!(
        ix1 < nx && (iy1 + 1) * nx <= heights.len(),
        "sample range outside the grid"
    );
    let (w, hgt) = (ix1 - ix0 + 1, iy1 - iy0 + 1);
    let z = |ix: usize, iy: usize| heights[iy * nx + ix];
    let span = ((z_range.1 - z_range.0) as f32).max(1e-6);
    let mut m = TriMesh {
        positions: Vec::with_capacity(w * hgt),
        normals: Vec::with_capacity(w * hgt),
        colors: Vec::with_capacity(w * hgt),
        triangles: Vec::with_capacity(2 * (w - 1) * (hgt - 1)),
    };
    for iy in iy0..=iy1 {
        for ix in ix0..=ix1 {
            let zc = z(ix, iy);
            m.positions.push([
                (origin[0] + ix as f64 * h) as f32,
                (origin[1] + iy as f64 * h) as f32,
                zc,
            ]);
            // Central differences (one-sided at the grid edge).
            let (xl, xr) = (ix.saturating_sub(1), (ix + 1).min(nx - 1));
            let ny_total = heights.len() / nx;
            let (yl, yr) = (iy.saturating_sub(1), (iy + 1).min(ny_total - 1));
            let dzdx = (z(xr, iy) - z(xl, iy)) / ((xr - xl).max(1) as f64 * h) as f32;
            let dzdy = (z(ix, yr) - z(ix, yl)) / ((yr - yl).max(1) as f64 * h) as f32;
            let n = [-dzdx, -dzdy, 1.0];
            let len = (n[0] * n[0] + n[1] * n[1] + 1.0).sqrt();
            m.normals.push([n[0] / len, n[1] / len, n[2] / len]);
            m.colors.push(height_color((zc - z_range.0 as f32) / span));
        }
    }
    for r in 0..hgt - 1 {
        for c in 0..w - 1 {
            let a = (r * w + c) as u32;
            let b = a + 1;
            let d = a + w as u32;
            let e = d + 1;
            m.triangles.push([a, b, e]);
            m.triangles.push([a, e, d]);
        }
    }
    m
}

/// A flat square of side `2 half_extent_m` at height 0 centred on `center` (the plane ground).
pub fn ground_quad(center: [f64; 2], half_extent_m: f64) -> TriMesh {
    let (cx, cy, e) = (center[0] as f32, center[1] as f32, half_extent_m as f32);
    TriMesh {
        positions: vec![
            [cx - e, cy - e, 0.0],
            [cx + e, cy - e, 0.0],
            [cx + e, cy + e, 0.0],
            [cx - e, cy + e, 0.0],
        ],
        normals: vec![[0.0, 0.0, 1.0]; 4],
        colors: vec![height_color(0.5); 4],
        triangles: vec![[0, 1, 2], [0, 2, 3]],
    }
}

/// Square chunks of `chunk` cells over an `nx x ny` sample grid: chunk `(cx, cy)`
/// covers samples `cx*chunk ..= min((cx+1)*chunk, nx-1)` (neighbours share edges).
pub fn chunk_sample_range(c: usize, chunk: usize, n: usize) -> (usize, usize) {
    let lo = c * chunk;
    (lo, ((c + 1) * chunk).min(n - 1))
}

/// Number of chunks along an axis of `n` samples.
pub fn chunk_count(chunk: usize, n: usize) -> usize {
    (n - 1).div_ceil(chunk)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_rotation_keeps_vectors() {
        assert_eq!(
            rotate_wxyz([1.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0]),
            [1.0, 2.0, 3.0]
        );
    }

    #[test]
    fn mesh_counts() {
        let heights = vec![0.0f32; 5 * 4];
        let m = heightfield_mesh(&heights, 5, [0.0, 0.0], 0.1, (1, 3), (0, 2), (0.0, 1.0));
        assert_eq!(m.positions.len(), 9);
        assert_eq!(m.triangles.len(), 8);
        assert!(m.normals.iter().all(|n| n == &[0.0, 0.0, 1.0]));
    }

    #[test]
    fn chunks_cover_the_grid() {
        assert_eq!(chunk_count(80, 901), 12);
        assert_eq!(chunk_sample_range(11, 80, 901), (880, 900));
        assert_eq!(chunk_count(80, 81), 1);
    }
}
