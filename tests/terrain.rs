//! Terrain tiles, the curriculum, and the heightfield scene in MuJoCo 2.2.2.

use rall::env::terrain::{
    Curriculum, LevelChange, Terrain, TerrainConfig, TerrainKind, TerrainProportions, TileKind,
    TERRAIN_NAME,
};
use rall::robot::{ControlConfig, Robot};
use rall::sim::{Data, GeomShape, Model, ObjKind};

const ALIENGO: &str = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml"));

/// 4 levels x 6 types of 8 m tiles, 1 m border: columns are
/// [slope pit, slope pyramid, rough slope, discrete, discrete, flat].
fn small_cfg() -> TerrainConfig {
    TerrainConfig {
        num_levels: 4,
        num_types: 6,
        border_size_m: 1.0,
        max_init_level: 2,
        proportions: TerrainProportions {
            smooth_slope: 2.0 / 6.0,
            rough_slope: 1.0 / 6.0,
            stairs_up: 0.0,
            stairs_down: 0.0,
            discrete: 2.0 / 6.0,
            flat: 1.0 / 6.0,
        },
        ..TerrainConfig::default()
    }
}

const PIT: usize = 0;
const PYRAMID: usize = 1;
const ROUGH: usize = 2;
const DISCRETE: usize = 3;
const FLAT: usize = 5;

/// Every sample height of tile (level, type), metres.
fn tile_samples(t: &Terrain, level: usize, ty: usize) -> Vec<f64> {
    let c = t.config();
    let h = c.horizontal_scale_m;
    let [x0, y0] = t.grid_origin_m();
    let ix0 = ((level as f64 * c.tile_length_m - x0) / h).round() as usize;
    let iy0 = ((ty as f64 * c.tile_width_m - y0) / h).round() as usize;
    let (nl, nw) = (
        (c.tile_length_m / h).round() as usize,
        (c.tile_width_m / h).round() as usize,
    );
    let mut out = Vec::with_capacity(nl * nw);
    for iy in iy0..iy0 + nw {
        for ix in ix0..ix0 + nl {
            out.push(t.sample_height_m(ix, iy));
        }
    }
    out
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |m, z| m.max(z.abs()))
}

#[test]
fn columns_get_the_configured_tile_kinds() {
    let t = Terrain::generate(&small_cfg(), 1);
    let kinds: Vec<TileKind> = (0..t.num_types()).map(|j| t.tile_kind(j)).collect();
    use TileKind::*;
    assert_eq!(
        kinds,
        [SlopePit, SlopePyramid, RoughSlope, Discrete, Discrete, Flat]
    );
    assert_eq!((t.num_levels(), t.num_types()), (4, 6));
    // 4 x 8 m + 2 x 1 m border along x, 6 x 8 m + 2 m along y, at 0.1 m (+1 sample).
    assert_eq!(t.grid_shape(), (341, 501));
    assert_eq!(t.heights_m().len(), 341 * 501);
    // The default config: 10 levels x 20 types, 901 x 1701 samples with the 5 m border.
    let d = TerrainConfig::default();
    d.validate().unwrap();
    let big = Terrain::generate(&d, 0);
    assert_eq!(big.grid_shape(), (901, 1701));
    let default_kinds: Vec<TileKind> = (0..20).map(|j| big.tile_kind(j)).collect();
    assert_eq!(
        &default_kinds[..6],
        &[
            SlopePit,
            SlopePit,
            SlopePit,
            SlopePyramid,
            SlopePyramid,
            SlopePyramid
        ]
    );
    assert!(default_kinds[6..12].iter().all(|&k| k == RoughSlope));
    assert!(default_kinds[12..18].iter().all(|&k| k == Discrete));
    assert!(default_kinds[18..].iter().all(|&k| k == Flat));
}

#[test]
fn flat_config_terrain_is_all_zeros() {
    let mut cfg = small_cfg();
    cfg.kind = TerrainKind::Flat;
    let t = Terrain::generate(&cfg, 7);
    assert!(t.heights_m().iter().all(|&z| z == 0.0));
    assert!((0..t.num_types()).all(|j| t.tile_kind(j) == TileKind::Flat));
    assert_eq!(t.tile_origin(2, 3), [20.0, 28.0, 0.0]);
    assert_eq!(t.height_at(13.37, 4.2), 0.0);
}

#[test]
fn smooth_slope_tiles_rise_by_their_slope() {
    let cfg = small_cfg();
    let v = cfg.vertical_scale_m;
    let t = Terrain::generate(&cfg, 3);
    for level in 0..cfg.num_levels {
        let slope = 0.4 * level as f64 / cfg.num_levels as f64;
        let (x0, y0) = (level as f64 * 8.0, PYRAMID as f64 * 8.0);
        let (cx, cy) = (x0 + 4.0, y0 + 4.0);
        // Along x at the tile's centre line: 0.5 m and 2.0 m from the edge, both on the face.
        let dz_x = t.height_at(x0 + 2.0, cy) - t.height_at(x0 + 0.5, cy);
        assert!(
            (dz_x - slope * 1.5).abs() <= v + 1e-6,
            "level {level}: x rise {dz_x}, want {}",
            slope * 1.5
        );
        // Along y, from the far edge towards the centre.
        let dz_y = t.height_at(cx, y0 + 8.0 - 2.0) - t.height_at(cx, y0 + 8.0 - 0.5);
        assert!(
            (dz_y - slope * 1.5).abs() <= v + 1e-6,
            "level {level}: y rise {dz_y}"
        );
        // Flat platform at slope x (4 - 1.5) m; the spawn point sits on it.
        let top = slope * 2.5;
        let o = t.tile_origin(level, PYRAMID);
        assert_eq!((o[0], o[1]), (cx, cy));
        assert!(
            (o[2] - top).abs() <= v / 2.0 + 1e-6,
            "level {level}: platform {} want {top}",
            o[2]
        );
        for (dx, dy) in [(0.0, 0.0), (1.4, 1.4), (-1.4, 0.7), (0.3, -1.4)] {
            assert!(
                (t.height_at(cx + dx, cy + dy) - o[2]).abs() < 1e-6,
                "platform not flat"
            );
        }
        // The pit is the mirror image.
        let p = t.tile_origin(level, PIT);
        assert!(
            (p[2] + top).abs() <= v / 2.0 + 1e-6,
            "level {level}: pit floor {}",
            p[2]
        );
        let dz_pit =
            t.height_at(level as f64 * 8.0 + 2.0, 4.0) - t.height_at(level as f64 * 8.0 + 0.5, 4.0);
        assert!(
            (dz_pit + slope * 1.5).abs() <= v + 1e-6,
            "level {level}: pit descent {dz_pit}"
        );
        // Heights are quantised to the vertical resolution.
        for z in tile_samples(&t, level, PYRAMID) {
            assert!(
                ((z / v) - (z / v).round()).abs() < 1e-3,
                "{z} not a multiple of {v}"
            );
        }
    }
}

#[test]
fn rough_slopes_carry_bounded_noise_around_the_pyramid() {
    let cfg = small_cfg();
    let t = Terrain::generate(&cfg, 5);
    for level in 0..cfg.num_levels {
        let d = level as f64 / cfg.num_levels as f64;
        let amp = 0.025 + 0.075 * d;
        let slope = 0.4 * d;
        let top = slope * 2.5;
        let z = tile_samples(&t, level, ROUGH);
        let lo = z.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = z.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        assert!(lo >= -amp - 0.005 - 1e-6, "level {level}: min {lo}");
        assert!(hi <= top + amp + 0.005 + 1e-6, "level {level}: max {hi}");
        // Noise is really there: the edge is not the smooth pyramid's 0 everywhere.
        let edge: Vec<f64> = (0..80)
            .map(|k| t.height_at(level as f64 * 8.0 + 0.05, 16.0 + k as f64 * 0.1))
            .collect();
        assert!(
            max_abs(&edge) > 0.005,
            "level {level}: no noise on the edge"
        );
        // The spawn platform stays flat.
        let o = t.tile_origin(level, ROUGH);
        assert!((o[2] - top).abs() <= 0.0025 + 1e-6);
        assert!((t.height_at(o[0] + 1.2, o[1] - 1.2) - o[2]).abs() < 1e-6);
    }
}

#[test]
fn discrete_obstacles_reach_the_expected_heights() {
    let cfg = small_cfg();
    let v = cfg.vertical_scale_m;
    let t = Terrain::generate(&cfg, 11);
    for level in 0..cfg.num_levels {
        let d = level as f64 / cfg.num_levels as f64;
        let k = ((0.05 + 0.2 * d) / v).round() as i64;
        let allowed = [0, k, -k, k / 2, -(k / 2)];
        for ty in [DISCRETE, DISCRETE + 1] {
            let z = tile_samples(&t, level, ty);
            for &s in &z {
                let units = (s / v).round() as i64;
                assert!(
                    (s / v - units as f64).abs() < 1e-3 && allowed.contains(&units),
                    "level {level}: height {s}"
                );
            }
            let m = max_abs(&z);
            assert!(
                m >= (k / 2) as f64 * v - 1e-6 && m <= k as f64 * v + 1e-6,
                "level {level}: max {m}"
            );
            // Both raised blocks and holes, covering a good share of the tile.
            assert!(
                z.iter().any(|&s| s > 0.0) && z.iter().any(|&s| s < 0.0),
                "level {level}: one-sided"
            );
            let covered = z.iter().filter(|&&s| s != 0.0).count() as f64 / z.len() as f64;
            assert!(covered > 0.2, "level {level}: only {covered} covered");
            // The spawn platform is cleared.
            let o = t.tile_origin(level, ty);
            assert_eq!(o[2], 0.0);
            assert_eq!(t.height_at(o[0] + 1.4, o[1] + 1.4), 0.0);
        }
    }
    // The top level in the default config: 0.05 + 0.2 x 0.9 = 0.23 m.
    let big = Terrain::generate(&TerrainConfig::default(), 2);
    let m = (12..18)
        .map(|ty| max_abs(&tile_samples(&big, 9, ty)))
        .fold(0.0, f64::max);
    assert!((m - 0.23).abs() < 1e-6, "top-level obstacle height {m}");
}

#[test]
fn stairs_climb_in_steps_of_the_expected_height() {
    let cfg = TerrainConfig {
        num_levels: 2,
        num_types: 2,
        border_size_m: 0.0,
        max_init_level: 0,
        proportions: TerrainProportions {
            smooth_slope: 0.0,
            rough_slope: 0.0,
            stairs_up: 0.5,
            stairs_down: 0.5,
            discrete: 0.0,
            flat: 0.0,
        },
        ..TerrainConfig::default()
    };
    let t = Terrain::generate(&cfg, 0);
    assert_eq!(
        (t.tile_kind(0), t.tile_kind(1)),
        (TileKind::StairsUp, TileKind::StairsDown)
    );
    let step = 0.05 + 0.18 * 0.5;
    // Level 1, stairs down (a pyramid): heights step by `step` every 0.3 m from the edge.
    for (k, x) in [0.1, 0.4, 0.7, 1.0].iter().enumerate() {
        let z = t.height_at(8.0 + x, 12.0);
        assert!(
            (z - k as f64 * step).abs() <= 0.0025 + 1e-6,
            "step {k}: {z}"
        );
    }
    let up = t.tile_origin(1, 0)[2];
    let down = t.tile_origin(1, 1)[2];
    assert!(
        up < -1.0 && (up + down).abs() < 1e-6,
        "pit {up} vs pyramid {down}"
    );
}

#[test]
fn level_zero_tiles_are_nearly_flat() {
    let cfg = small_cfg();
    let t = Terrain::generate(&cfg, 9);
    for ty in 0..cfg.num_types {
        let z = tile_samples(&t, 0, ty);
        let bound = match t.tile_kind(ty) {
            TileKind::SlopePit | TileKind::SlopePyramid | TileKind::Flat => 0.0,
            TileKind::RoughSlope => 0.025,
            TileKind::Discrete => 0.05,
            TileKind::StairsUp | TileKind::StairsDown => unreachable!(),
        };
        assert!(
            max_abs(&z) <= bound + 1e-6,
            "type {ty}: {} > {bound}",
            max_abs(&z)
        );
        assert!(t.tile_origin(0, ty)[2].abs() < 1e-9);
    }
    // The border is flat ground at 0.
    assert_eq!(t.height_at(-0.5, -0.5), 0.0);
    assert_eq!(t.height_at(32.5, 20.0), 0.0);
}

#[test]
fn generation_is_deterministic_in_the_seed() {
    let cfg = small_cfg();
    let a = Terrain::generate(&cfg, 42);
    let b = Terrain::generate(&cfg, 42);
    let c = Terrain::generate(&cfg, 43);
    assert_eq!(a.heights_m(), b.heights_m());
    assert_ne!(a.heights_m(), c.heights_m());
    for level in 1..cfg.num_levels {
        assert_ne!(
            tile_samples(&a, level, ROUGH),
            tile_samples(&c, level, ROUGH),
            "rough level {level}"
        );
        assert_ne!(
            tile_samples(&a, level, DISCRETE),
            tile_samples(&c, level, DISCRETE)
        );
        // Smooth tiles do not depend on the seed.
        assert_eq!(
            tile_samples(&a, level, PYRAMID),
            tile_samples(&c, level, PYRAMID)
        );
        assert_eq!(a.tile_origin(level, PIT), c.tile_origin(level, PIT));
    }
}

// --- curriculum ------------------------------------------------------------

#[test]
fn curriculum_starts_at_low_levels_with_types_spread_over_envs() {
    let cfg = small_cfg();
    let c = Curriculum::new(&cfg, 12, 0);
    assert_eq!(c.types(), &[0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5]);
    assert_eq!(Curriculum::new(&cfg, 3, 0).types(), &[0, 2, 4]);
    let many = Curriculum::new(&cfg, 400, 1);
    assert!(many.levels().iter().all(|&l| l <= cfg.max_init_level));
    for l in 0..=cfg.max_init_level {
        assert!(many.levels().contains(&l), "initial level {l} never drawn");
    }
    assert!(
        (many.mean_level() - 1.0).abs() < 0.2,
        "mean {}",
        many.mean_level()
    );
    assert_eq!(many.levels(), Curriculum::new(&cfg, 400, 1).levels());
    assert_ne!(many.levels(), Curriculum::new(&cfg, 400, 2).levels());
}

#[test]
fn curriculum_promotes_demotes_and_floors_at_zero() {
    let cfg = small_cfg(); // 8 m tiles: promotion above 4 m walked.
    let mut c = Curriculum::new(&cfg, 2, 0);
    c.set_level(0, 1);
    assert_eq!(c.update(0, 4.5, 0.0), LevelChange::Promoted);
    assert_eq!(c.level(0), 2);
    assert_eq!(
        c.update(0, 4.0, 0.0),
        LevelChange::Unchanged,
        "exactly half a tile is not more"
    );
    // Walked under half the commanded 10 m: demoted.
    assert_eq!(c.update(0, 3.9, 10.0), LevelChange::Demoted);
    assert_eq!(c.level(0), 1);
    // Half or more of the command: stays.
    assert_eq!(c.update(0, 3.0, 6.0), LevelChange::Unchanged);
    assert_eq!(c.level(0), 1);
    // Promotion wins over demotion (4.5 m > 4 m although < half of 20 m).
    assert_eq!(c.update(0, 4.5, 20.0), LevelChange::Promoted);
    assert_eq!(c.level(0), 2);
    // Never below 0.
    c.set_level(1, 0);
    assert_eq!(c.update(1, 0.0, 10.0), LevelChange::Unchanged);
    assert_eq!(c.level(1), 0);
    assert_eq!(c.mean_level(), 1.0);
}

#[test]
fn curriculum_past_the_top_level_goes_to_a_random_level() {
    let cfg = small_cfg();
    let top = cfg.num_levels - 1;
    let mut c = Curriculum::new(&cfg, 1, 5);
    c.set_level(0, top - 1);
    assert_eq!(c.update(0, 5.0, 0.0), LevelChange::Promoted);
    assert_eq!(c.level(0), top);
    let mut seen = vec![false; cfg.num_levels];
    for _ in 0..200 {
        c.set_level(0, top);
        assert_eq!(c.update(0, 5.0, 0.0), LevelChange::Wrapped);
        assert!(c.level(0) <= top);
        seen[c.level(0)] = true;
    }
    assert!(seen.iter().all(|&s| s), "wrapped levels {seen:?}");
}

#[test]
fn curriculum_does_not_depend_on_update_order() {
    let cfg = small_cfg();
    let run = |order: &[usize]| {
        let mut c = Curriculum::new(&cfg, 4, 9);
        for round in 0..30 {
            for &e in order {
                let walked = if (round + e).is_multiple_of(3) {
                    1.0
                } else {
                    6.0
                };
                c.update(e, walked, 8.0);
            }
        }
        c.levels().to_vec()
    };
    assert_eq!(run(&[0, 1, 2, 3]), run(&[3, 1, 0, 2]));
}

// --- config ----------------------------------------------------------------

#[test]
fn validate_names_the_offending_key() {
    assert!(TerrainConfig::default().validate().is_ok());
    assert!(small_cfg().validate().is_ok());
    type Edit = fn(&mut TerrainConfig);
    let cases: &[(Edit, &str)] = &[
        (|c| c.tile_length_m = -8.0, "terrain.tile_length_m"),
        (|c| c.tile_width_m = 0.0, "terrain.tile_width_m"),
        (|c| c.tile_length_m = 8.05, "terrain.tile_length_m"),
        (|c| c.horizontal_scale_m = 0.0, "terrain.horizontal_scale_m"),
        (|c| c.vertical_scale_m = -0.005, "terrain.vertical_scale_m"),
        // a quantum that rounds every feature away: the terrain would be flat
        (|c| c.vertical_scale_m = 1e30, "terrain.vertical_scale_m"),
        (|c| c.vertical_scale_m = 0.03, "terrain.vertical_scale_m"),
        (|c| c.tile_length_m = 1e30, "terrain.tile_length_m"),
        (|c| c.border_size_m = -1.0, "terrain.border_size_m"),
        (|c| c.platform_size_m = 9.0, "terrain.platform_size_m"),
        (|c| c.num_levels = 0, "terrain.num_levels"),
        (|c| c.num_types = 0, "terrain.num_types"),
        (|c| c.max_init_level = 10, "terrain.max_init_level"),
        (|c| c.proportions.flat = 0.2, "terrain.proportions"),
        (
            |c| c.proportions.discrete = -0.1,
            "terrain.proportions.discrete",
        ),
        (
            |c| c.proportions.rough_slope = f64::NAN,
            "terrain.proportions.rough_slope",
        ),
        (|c| c.num_levels = 100_000, "terrain grid"),
    ];
    for (edit, key) in cases {
        let mut c = TerrainConfig::default();
        edit(&mut c);
        let err = c.validate().expect_err(key);
        assert!(err.contains(key), "error {err:?} does not name {key}");
    }
}

#[test]
fn config_parses_from_toml_and_refuses_unknown_keys() {
    let c: TerrainConfig =
        toml::from_str("kind = \"flat\"\nnum_levels = 3\nmax_init_level = 1\n").unwrap();
    assert_eq!(c.kind, TerrainKind::Flat);
    assert_eq!((c.num_levels, c.num_types, c.tile_length_m), (3, 20, 8.0));
    c.validate().unwrap();
    let c: TerrainConfig = toml::from_str("[proportions]\ndiscrete = 0.4\nflat = 0.0\n").unwrap();
    assert_eq!(c.proportions.discrete, 0.4);
    assert_eq!(c.proportions.smooth_slope, 0.3);
    assert!(toml::from_str::<TerrainConfig>("kind = \"Rough\"").is_err());
    let err = toml::from_str::<TerrainConfig>("tile_size = 8.0")
        .unwrap_err()
        .to_string();
    assert!(err.contains("tile_size"), "{err}");
    assert!(toml::from_str::<TerrainConfig>("[proportions]\nstairs = 0.1").is_err());
}

// --- MuJoCo scene --------------------------------------------------------------

/// Adds vertical probes: spheres of radius `r` on z slide joints above each point.
fn with_probes(xml: &str, points: &[(f64, f64, f64)], r: f64) -> String {
    let mut bodies = String::from("  <worldbody>\n");
    for (i, (x, y, z)) in points.iter().enumerate() {
        bodies += &format!(
            "    <body name=\"probe{i}\" pos=\"{x} {y} {}\">\n      \
             <joint name=\"probe{i}\" type=\"slide\" axis=\"0 0 1\" damping=\"2\"/>\n      \
             <geom type=\"sphere\" size=\"{r}\" mass=\"0.1\" contype=\"1\" conaffinity=\"0\"/>\n    \
             </body>\n",
            z + 0.15
        );
    }
    bodies += "  </worldbody>\n";
    // The robot's keyframe fixes nq; the probes add joints, so drop it here.
    let (k0, k1) = (
        xml.find("<keyframe>").unwrap(),
        xml.find("</keyframe>").unwrap() + "</keyframe>".len(),
    );
    let xml = format!("{}{}", &xml[..k0], &xml[k1..]);
    let end = xml.rfind("</mujoco>").unwrap();
    format!("{}{}{}", &xml[..end], bodies, &xml[end..])
}

/// A point deep inside a raised discrete block (0.4 m around it at one height).
fn block_top(t: &Terrain, level: usize, ty: usize) -> (f64, f64) {
    let (x0, y0) = (level as f64 * 8.0, ty as f64 * 8.0);
    for i in 5..75 {
        for j in 5..75 {
            let (x, y) = (x0 + i as f64 * 0.1, y0 + j as f64 * 0.1);
            let z = t.height_at(x, y);
            if z > 0.0
                && (-4..=4).all(|a| {
                    (-4..=4).all(|b| t.height_at(x + a as f64 * 0.1, y + b as f64 * 0.1) == z)
                })
            {
                return (x, y);
            }
        }
    }
    panic!("no raised block in tile ({level}, {ty})");
}

#[test]
fn dropped_spheres_rest_on_the_generated_heights() {
    let t = Terrain::generate(&small_cfg(), 4);
    let block = block_top(&t, 3, DISCRETE);
    let xy = [
        (20.0, 12.0),                    // pyramid platform, level 2 (0.5 m)
        (17.0, 12.0),                    // pyramid face rising along +x
        (20.0, 9.0),                     // pyramid face rising along +y
        (22.7, 13.9),                    // pyramid face falling along +x
        (28.0, 6.5),                     // pit face, level 3
        (28.0, 4.0),                     // pit floor (-0.75 m)
        (12.0, FLAT as f64 * 8.0 + 4.0), // flat tile
        (-0.5, 30.0),                    // border
        block,                           // top of a discrete block
    ];
    let pts: Vec<(f64, f64, f64)> = xy.iter().map(|&(x, y)| (x, y, t.height_at(x, y))).collect();
    // The points really are at different heights (else orientation would go unchecked).
    assert!(pts[0].2 > 0.45 && pts[5].2 < -0.7 && pts[8].2 > 0.05);
    assert!((pts[1].2 - 0.2).abs() < 1e-6 && (pts[2].2 - 0.2).abs() < 1e-6);
    let r = 0.03;
    let xml = with_probes(&t.scene_xml(ALIENGO).unwrap(), &pts, r);
    let mut model = Model::from_xml_str(&xml, "terrain probes").unwrap();
    let g = model.require_id(ObjKind::Geom, TERRAIN_NAME).unwrap();
    assert_eq!(model.geom_shape(g), GeomShape::Hfield);
    let hf = model.geom_hfield(g).unwrap();
    assert_eq!(
        model.hfield_shape(hf),
        (501, 341),
        "rows along y, columns along x"
    );
    assert!(
        model.hfield_data(hf).iter().all(|&v| v == 0.0),
        "no data before upload"
    );
    t.upload(&mut model).unwrap();
    let data = model.hfield_data(hf);
    assert!(data.iter().all(|&v| (0.0..=1.0).contains(&v)));
    assert!(data.contains(&0.0) && data.contains(&1.0));

    let mut d = Data::new(&model).unwrap();
    for _ in 0..300 {
        d.step(&model).unwrap();
    }
    for (i, &(x, y, z)) in pts.iter().enumerate() {
        let b = model
            .require_id(ObjKind::Body, &format!("probe{i}"))
            .unwrap();
        let got = d.xpos()[b][2];
        // On a plane of gradient g the centre of a resting sphere is r sqrt(1 + |g|^2) above it.
        let e = 0.05;
        let gx = (t.height_at(x + e, y) - t.height_at(x - e, y)) / (2.0 * e);
        let gy = (t.height_at(x, y + e) - t.height_at(x, y - e)) / (2.0 * e);
        let want = z + r * (1.0 + gx * gx + gy * gy).sqrt();
        assert!(
            (got - want).abs() < 0.005,
            "probe {i} at ({x}, {y}): rests at {got:.4}, terrain says {want:.4}"
        );
        assert!(
            d.qvel()[model.joint_dof_adr(
                model
                    .require_id(ObjKind::Joint, &format!("probe{i}"))
                    .unwrap()
            )]
            .abs()
                < 1e-2
        );
    }
}

#[test]
fn scenes_load_for_both_kinds_and_robot_wraps_the_rough_one() {
    // Rough: the robot model loads and stands at a tile origin.
    let t = Terrain::generate(&small_cfg(), 8);
    let mut model = Model::from_xml_str(&t.scene_xml(ALIENGO).unwrap(), "rough scene").unwrap();
    t.upload(&mut model).unwrap();
    let robot = Robot::new(model, ControlConfig::default()).unwrap();
    assert!(rall::robot::has_ground(robot.model()));
    assert_eq!(robot.model().nhfield(), 1);

    // Flat: a plane named "terrain", no hfield; upload is a no-op.
    let mut cfg = small_cfg();
    cfg.kind = TerrainKind::Flat;
    let flat = Terrain::generate(&cfg, 8);
    let mut model = Model::from_xml_str(&flat.scene_xml(ALIENGO).unwrap(), "flat scene").unwrap();
    let g = model.require_id(ObjKind::Geom, TERRAIN_NAME).unwrap();
    assert_eq!(model.geom_shape(g), GeomShape::Plane);
    assert_eq!(model.geom_collision_bits(g), (0, 1));
    assert_eq!(model.nhfield(), 0);
    flat.upload(&mut model).unwrap();
    Robot::new(model, ControlConfig::default()).unwrap();

    // upload refuses models it did not build.
    let mut bare = Model::from_xml_str(ALIENGO, "aliengo").unwrap();
    let err = t.upload(&mut bare).unwrap_err();
    assert!(err.contains(TERRAIN_NAME), "{err}");
    let mut other_cfg = small_cfg();
    other_cfg.num_levels = 3;
    let other = Terrain::generate(&other_cfg, 8);
    let mut other_model = Model::from_xml_str(&other.scene_xml(ALIENGO).unwrap(), "other").unwrap();
    assert!(t.upload(&mut other_model).is_err());
    assert!(t.scene_xml("<mujoco>").is_err());
}

#[test]
fn robot_stands_on_a_tile_origin() {
    let t = Terrain::generate(&small_cfg(), 8);
    let mut model = Model::from_xml_str(&t.scene_xml(ALIENGO).unwrap(), "rough scene").unwrap();
    t.upload(&mut model).unwrap();
    let mut robot = Robot::new(model, ControlConfig::default()).unwrap();
    let o = t.tile_origin(3, PYRAMID);
    let a = robot.layout.root_qpos_adr;
    let z0 = robot.data().qpos()[a + 2];
    robot.data_mut().qpos_mut()[a] = o[0];
    robot.data_mut().qpos_mut()[a + 1] = o[1];
    robot.data_mut().qpos_mut()[a + 2] = o[2] + z0;
    let targets = robot.default_q_rad;
    for _ in 0..200 {
        robot.pd_substep(&targets).unwrap();
    }
    let p = robot.base_pos_m();
    assert!(
        (p[0] - o[0]).abs() < 0.1 && (p[1] - o[1]).abs() < 0.1,
        "drifted to {p:?}"
    );
    let height = p[2] - o[2];
    assert!(
        height > 0.3 && height < 0.45,
        "trunk {height:.3} m above the platform"
    );
}
