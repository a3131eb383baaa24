//! MuJoCo -> rerun geometry conventions (pure functions, no recording): a capsule
//! and rotated boxes land where MuJoCo puts them, with hand-computed end points
//! and corners, and the heightfield mesh matches the terrain samples.

use rall::sim::{Data, GeomShape, Model, ObjKind};
use rall::viz::convert::{
    box_from_mujoco, capsule_from_mujoco, geom_primitive, heightfield_mesh, quat_wxyz_to_xyzw,
    rotate_wxyz, Primitive,
};

const S: f64 = std::f64::consts::FRAC_1_SQRT_2;

fn close(a: [f32; 3], b: [f64; 3], tol: f64) -> bool {
    (0..3).all(|i| (a[i] as f64 - b[i]).abs() <= tol)
}

#[track_caller]
fn assert_close(a: [f32; 3], b: [f64; 3]) {
    assert!(close(a, b, 1e-6), "{a:?} != {b:?}");
}

#[test]
fn quaternions_are_reordered_wxyz_to_xyzw() {
    assert_eq!(
        quat_wxyz_to_xyzw([0.1, 0.2, 0.3, 0.4]),
        [0.2, 0.3, 0.4, 0.1]
    );
}

#[test]
fn capsule_rotated_about_x_has_hand_computed_end_points() {
    // MuJoCo: radius 0.02, half-length 0.1, centred at (1, 2, 3), rotated +90 deg
    // about x, so its local z axis points along world -y: end caps at y = 2 -+ 0.1.
    let c = capsule_from_mujoco([0.02, 0.1, 0.0], [1.0, 2.0, 3.0], [S, S, 0.0, 0.0]);
    assert!((c.length - 0.2).abs() < 1e-7 && (c.radius - 0.02).abs() < 1e-7);
    assert_eq!(c.quat_xyzw, [S as f32, 0.0, 0.0, S as f32]);
    // rerun starts the capsule at the end R (0, 0, -h) from the centre = (1, 2.1, 3)
    // and extends it along R (0, 0, 1) = (0, -1, 0) by the full length.
    let (a, b) = c.endpoints();
    assert_close(a, [1.0, 2.1, 3.0]);
    assert_close(b, [1.0, 1.9, 3.0]);
}

#[test]
fn tilted_capsule_is_centred_where_mujoco_centres_it() {
    // 60 deg about y: axis = (sin 60, 0, cos 60).
    let half = std::f64::consts::PI / 6.0;
    let q = [half.cos(), 0.0, half.sin(), 0.0];
    let c = capsule_from_mujoco([0.05, 0.2, 0.0], [0.0, 0.0, 1.0], q);
    let (a, b) = c.endpoints();
    let (s60, c60) = (3f64.sqrt() / 2.0, 0.5);
    assert_close(a, [-0.2 * s60, 0.0, 1.0 - 0.2 * c60]);
    assert_close(b, [0.2 * s60, 0.0, 1.0 + 0.2 * c60]);
}

#[test]
fn box_rotated_about_z_has_hand_computed_corners() {
    // Half-sizes (0.3, 0.1, 0.05) at (0.5, 0, 0.2), +90 deg about z: x -> y, y -> -x.
    let b = box_from_mujoco([0.3, 0.1, 0.05], [0.5, 0.0, 0.2], [S, 0.0, 0.0, S]);
    assert_eq!(b.half_size, [0.3, 0.1, 0.05]);
    assert_close(b.center, [0.5, 0.0, 0.2]);
    let corners = b.corners();
    // Corner 7 is local (+0.3, +0.1, +0.05) -> world (0.5 - 0.1, 0 + 0.3, 0.25).
    assert_close(corners[7], [0.4, 0.3, 0.25]);
    // Corner 0 is local (-0.3, -0.1, -0.05) -> (0.6, -0.3, 0.15).
    assert_close(corners[0], [0.6, -0.3, 0.15]);
    // The footprint is 0.2 wide along x and 0.6 long along y.
    let xs: Vec<f32> = corners.iter().map(|c| c[0]).collect();
    let ys: Vec<f32> = corners.iter().map(|c| c[1]).collect();
    let span = |v: &[f32]| {
        v.iter().cloned().fold(f32::MIN, f32::max) - v.iter().cloned().fold(f32::MAX, f32::min)
    };
    assert!((span(&xs) - 0.2).abs() < 1e-6 && (span(&ys) - 0.6).abs() < 1e-6);
}

#[test]
fn box_rotated_45_deg_has_hand_computed_corner() {
    // Unit half-size along x only, 45 deg about z: the +x face centre goes to (s, s, 0).
    let half = std::f64::consts::PI / 8.0;
    let b = box_from_mujoco(
        [1.0, 0.0, 0.0],
        [0.0; 3],
        [half.cos(), 0.0, 0.0, half.sin()],
    );
    assert_close(b.corners()[7], [S, S, 0.0]);
}

/// A rotated body carrying a capsule and a rotated box: the primitive placed by the
/// body's world pose (what the viewer composes: body Transform3D, then the geom)
/// lands on MuJoCo's own geom_xpos, and the capsule axis matches by hand.
#[test]
fn body_pose_and_geom_primitive_compose_to_mujoco_world_positions() {
    let xml = r#"<mujoco>
      <worldbody>
        <body name="b" pos="1 2 0.5" quat="0.7071067811865476 0 0 0.7071067811865476">
          <freejoint/>
          <geom name="cap" type="capsule" size="0.03 0.15" pos="0.2 0 0" quat="0.7071067811865476 0 0.7071067811865476 0"/>
          <geom name="box" type="box" size="0.1 0.05 0.02" pos="0 0.1 0" euler="0.3 0.2 0.1"/>
          <geom name="ball" type="sphere" size="0.04" pos="0 0 -0.1"/>
        </body>
      </worldbody>
    </mujoco>"#;
    let model = Model::from_xml_str(xml, "viz test").expect("model");
    let data = Data::new(&model).expect("data");
    let body = model.id(ObjKind::Body, "b").unwrap();
    let (bp, bq) = (data.xpos()[body], data.xquat()[body]);
    let world = |p: [f32; 3]| {
        let r = rotate_wxyz(bq, [p[0] as f64, p[1] as f64, p[2] as f64]);
        [bp[0] + r[0], bp[1] + r[1], bp[2] + r[2]]
    };
    for g in 0..model.ngeom() {
        let prim = geom_primitive(
            model.geom_shape(g),
            model.geom_size()[g],
            model.geom_pos()[g],
            model.geom_quat()[g],
        )
        .expect("a primitive");
        let centre = match prim {
            Primitive::Capsule(c) => {
                let (a, b) = c.endpoints();
                let (wa, wb) = (world(a), world(b));
                if model.name(ObjKind::Geom, g) == "cap" {
                    // By hand: +90 deg about y maps the capsule's local z to body +x,
                    // the body's +90 deg about z maps body +x to world +y. Centre =
                    // (1, 2, 0.5) + Rz(90) (0.2, 0, 0) = (1, 2.2, 0.5); ends at y -+ 0.15,
                    // rerun's start being the lower one.
                    assert!(
                        close(
                            [wa[0] as f32, wa[1] as f32, wa[2] as f32],
                            [1.0, 2.05, 0.5],
                            1e-5
                        ),
                        "{wa:?}"
                    );
                    assert!(
                        close(
                            [wb[0] as f32, wb[1] as f32, wb[2] as f32],
                            [1.0, 2.35, 0.5],
                            1e-5
                        ),
                        "{wb:?}"
                    );
                }
                [
                    (wa[0] + wb[0]) / 2.0,
                    (wa[1] + wb[1]) / 2.0,
                    (wa[2] + wb[2]) / 2.0,
                ]
            }
            Primitive::Box(b) => world(b.center),
            Primitive::Ellipsoid(e) => world(e.center),
            Primitive::Cylinder(c) => world(c.center),
        };
        let want = data.geom_xpos()[g];
        assert!(
            (0..3).all(|i| (centre[i] - want[i]).abs() < 1e-5),
            "geom {} at {centre:?}, MuJoCo {want:?}",
            model.name(ObjKind::Geom, g)
        );
    }
    assert_eq!(model.geom_shape(2), GeomShape::Sphere);
}

#[test]
fn planes_and_heightfields_are_not_primitives() {
    assert!(geom_primitive(GeomShape::Plane, [0.0; 3], [0.0; 3], [1.0, 0.0, 0.0, 0.0]).is_none());
    assert!(geom_primitive(GeomShape::Hfield, [0.0; 3], [0.0; 3], [1.0, 0.0, 0.0, 0.0]).is_none());
}

#[test]
fn heightfield_mesh_follows_the_sample_layout() {
    // 4 x 3 samples, h = 0.5, origin (-1, -2); z = ix + 10 iy.
    let (nx, ny) = (4, 3);
    let heights: Vec<f32> = (0..ny)
        .flat_map(|iy| (0..nx).map(move |ix| (ix + 10 * iy) as f32))
        .collect();
    let m = heightfield_mesh(&heights, nx, [-1.0, -2.0], 0.5, (1, 3), (1, 2), (0.0, 23.0));
    assert_eq!(m.positions.len(), 3 * 2);
    assert_eq!(m.triangles.len(), 2 * 2);
    // First vertex: sample (1, 1) at (-0.5, -1.5), z = 11; last: (3, 2) at (0.5, -1), z = 23.
    assert_eq!(m.positions[0], [-0.5, -1.5, 11.0]);
    assert_eq!(m.positions[5], [0.5, -1.0, 23.0]);
    // Triangles are counter-clockwise from above: their normals point up (+z).
    for t in &m.triangles {
        let p = |i: u32| m.positions[i as usize];
        let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
        let (u, v) = ([b[0] - a[0], b[1] - a[1]], [c[0] - a[0], c[1] - a[1]]);
        assert!(
            u[0] * v[1] - u[1] * v[0] > 0.0,
            "triangle {t:?} is clockwise"
        );
    }
    assert!(m.normals.iter().all(|n| n[2] > 0.0));
}
