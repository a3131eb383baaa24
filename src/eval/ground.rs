//! The ground of the evaluation scenarios: a plane, a random rough field, a
//! platform, or the race course, as one MuJoCo heightfield (plus a plane under it
//! as a safety net where the field ends).
//!
//! The grid is a [`Heightfield`], the
//! training terrain's own: metres, row-major with the row along y and the column
//! along x (`heights_m()[iy * nx + ix]` is the point `origin + (ix h, iy h)`),
//! which is MuJoCo's hfield layout.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::env::heightfield::{Heightfield, HfieldSpec};
use crate::sim::Model;

/// Name of the ground geom (and of its hfield asset) in scenario scenes.
pub const GROUND_NAME: &str = "ground";
/// The hfield of every ground: a 0.5 m block, at least 1 mm of elevation, and
/// the range of the samples alone.
const HFIELD_SPEC: HfieldSpec = HfieldSpec {
    base_m: 0.5,
    min_elevation_m: 0.001,
    range_spans_zero: false,
};
/// The safety-net plane lies this far under the lowest ground, m.
const NET_DEPTH_M: f64 = 0.05;
/// Collision bits and look of every ground geom.
const GROUND_ATTRS: &str = "contype=\"0\" conaffinity=\"1\" condim=\"3\" \
     friction=\"1.0 0.005 0.0001\" rgba=\"0.55 0.5 0.45 1\"";

/// Random rough ground (legged_gym's `random_uniform_terrain`: uniform heights on
/// a coarse lattice, interpolated).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RoughParams {
    /// The field spans [-half_extent, half_extent] in x and y, m.
    pub half_extent_m: f64,
    /// Heights are uniform in [-amplitude, amplitude], m.
    pub amplitude_m: f64,
    /// Spacing of the random lattice, m.
    pub lattice_m: f64,
    /// Half side of the flat square at height 0 around the spawn point, m.
    pub spawn_pad_m: f64,
    pub horizontal_scale_m: f64,
    pub vertical_scale_m: f64,
}

impl Default for RoughParams {
    fn default() -> Self {
        RoughParams {
            half_extent_m: 25.0,
            amplitude_m: 0.05,
            lattice_m: 0.2,
            spawn_pad_m: 0.6,
            horizontal_scale_m: 0.1,
            vertical_scale_m: 0.005,
        }
    }
}

/// What a stretch of the race course holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SegmentKind {
    /// The raised start; its end is the platform drop.
    Platform,
    Flat,
    /// Random blocks and holes.
    Obstacles,
    /// Uniform random heights.
    Rough,
}

/// One stretch of the race course, x in [x0, x1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Segment {
    pub kind: SegmentKind,
    pub x0_m: f64,
    pub x1_m: f64,
}

/// The race course: a straight track along +x mixing normal stretches with
/// hazards. The robot starts at x = 0 on the platform.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RaceTrackParams {
    /// Height of the start platform (the drop at its end), m.
    pub drop_height_m: f64,
    /// Stretches in order, starting at `start_m`; each (kind, length m).
    pub layout: Vec<(SegmentKind, f64)>,
    /// x where the first stretch starts (behind the robot), m.
    pub start_m: f64,
    /// Track width (centred on y = 0), m.
    pub width_m: f64,
    /// Flat run-out after the last stretch, m.
    pub run_out_m: f64,
    /// Block heights are +-h and +-h/2, m.
    pub obstacle_height_m: f64,
    /// Block sides are uniform in this range, m.
    pub obstacle_size_m: [f64; 2],
    /// Blocks per square metre of obstacle stretch.
    pub obstacle_density_per_m2: f64,
    pub rough_amplitude_m: f64,
    pub rough_lattice_m: f64,
    pub horizontal_scale_m: f64,
    pub vertical_scale_m: f64,
}

impl Default for RaceTrackParams {
    fn default() -> Self {
        use SegmentKind::*;
        RaceTrackParams {
            drop_height_m: 0.2,
            layout: vec![
                (Platform, 4.5),
                (Flat, 1.5),
                (Obstacles, 2.5),
                (Flat, 1.5),
                (Rough, 2.5),
                (Flat, 1.5),
                (Obstacles, 2.0),
                (Flat, 1.5),
                (Rough, 2.5),
            ],
            start_m: -2.5,
            width_m: 6.0,
            run_out_m: 6.0,
            obstacle_height_m: 0.08,
            obstacle_size_m: [0.3, 0.8],
            obstacle_density_per_m2: 1.2,
            rough_amplitude_m: 0.06,
            rough_lattice_m: 0.2,
            horizontal_scale_m: 0.05,
            vertical_scale_m: 0.005,
        }
    }
}

/// A heightfield ground.
#[derive(Debug, Clone)]
pub struct Ground {
    /// The height grid.
    field: Heightfield,
    /// Race course stretches (empty for other grounds).
    segments: Vec<Segment>,
}

impl Ground {
    /// A flat field of `nx x ny` samples `h` apart, sample (0, 0) at `origin_m`.
    pub fn flat(origin_m: [f64; 2], h: f64, nx: usize, ny: usize) -> Ground {
        Ground {
            field: Heightfield::flat(origin_m, h, (nx, ny), HFIELD_SPEC),
            segments: Vec::new(),
        }
    }

    /// Random rough ground centred on the origin, with a flat spawn pad.
    pub fn rough(p: &RoughParams, seed: u64) -> Ground {
        let h = p.horizontal_scale_m;
        let n = (2.0 * p.half_extent_m / h).round() as usize + 1;
        let mut g = Ground::flat([-p.half_extent_m, -p.half_extent_m], h, n, n);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let noise = LatticeNoise::new(
            [-p.half_extent_m, -p.half_extent_m],
            [p.half_extent_m, p.half_extent_m],
            p.lattice_m,
            p.amplitude_m,
            p.vertical_scale_m,
            &mut rng,
        );
        for iy in 0..n {
            for ix in 0..n {
                let [x, y] = g.point(ix, iy);
                if x.abs() <= p.spawn_pad_m && y.abs() <= p.spawn_pad_m {
                    continue;
                }
                g.set(ix, iy, noise.at(x, y), p.vertical_scale_m);
            }
        }
        g
    }

    /// The race course (deterministic in `seed`).
    pub fn race_track(p: &RaceTrackParams, seed: u64) -> Ground {
        let h = p.horizontal_scale_m;
        let length: f64 = p.layout.iter().map(|(_, l)| l).sum::<f64>() + p.run_out_m;
        let nx = (length / h).round() as usize + 1;
        let ny = (p.width_m / h).round() as usize + 1;
        let y0 = -p.width_m / 2.0;
        let mut g = Ground::flat([p.start_m, y0], h, nx, ny);
        let mut x = p.start_m;
        for (i, &(kind, len)) in p.layout.iter().enumerate() {
            g.segments.push(Segment {
                kind,
                x0_m: x,
                x1_m: x + len,
            });
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            rng.set_stream(i as u64);
            g.fill_segment(p, kind, x, x + len, &mut rng);
            x += len;
        }
        g.segments.push(Segment {
            kind: SegmentKind::Flat,
            x0_m: x,
            x1_m: x + p.run_out_m,
        });
        g
    }

    fn fill_segment(
        &mut self,
        p: &RaceTrackParams,
        kind: SegmentKind,
        x0: f64,
        x1: f64,
        rng: &mut ChaCha8Rng,
    ) {
        let v = p.vertical_scale_m;
        let (_, ny) = self.grid_shape();
        let (ya, yb) = (self.point(0, 0)[1], self.point(0, ny - 1)[1]);
        match kind {
            SegmentKind::Flat => {}
            SegmentKind::Platform => self.fill_box(x0, x1, ya, yb, p.drop_height_m, v),
            SegmentKind::Rough => {
                let noise = LatticeNoise::new(
                    [x0, ya],
                    [x1, yb],
                    p.rough_lattice_m,
                    p.rough_amplitude_m,
                    v,
                    rng,
                );
                for iy in 0..ny {
                    for ix in self.columns(x0, x1) {
                        let [x, y] = self.point(ix, iy);
                        self.set(ix, iy, noise.at(x, y), v);
                    }
                }
            }
            SegmentKind::Obstacles => {
                let area = (x1 - x0) * (yb - ya);
                let count = (area * p.obstacle_density_per_m2).round() as usize;
                let hh = p.obstacle_height_m;
                let levels = [-hh, -hh / 2.0, hh / 2.0, hh];
                let [s0, s1] = p.obstacle_size_m;
                for _ in 0..count {
                    let (sx, sy) = (rng.gen_range(s0..=s1), rng.gen_range(s0..=s1));
                    let cx = rng.gen_range(x0..=(x1 - sx).max(x0));
                    let cy = rng.gen_range(ya..=(yb - sy).max(ya));
                    let z = levels[rng.gen_range(0..levels.len())];
                    self.fill_box(cx, (cx + sx).min(x1), cy, cy + sy, z, v);
                }
            }
        }
    }

    /// Column indices with x in [x0, x1).
    fn columns(&self, x0: f64, x1: f64) -> std::ops::Range<usize> {
        let [ox, _] = self.grid_origin_m();
        let h = self.horizontal_scale_m();
        let nx = self.grid_shape().0;
        let a = ((x0 - ox) / h).ceil().max(0.0) as usize;
        let b = ((x1 - ox) / h).ceil().max(0.0) as usize;
        a.min(nx)..b.min(nx)
    }

    /// Sets the samples with x in [x0, x1), y in [y0, y1] to `z`.
    fn fill_box(&mut self, x0: f64, x1: f64, y0: f64, y1: f64, z: f64, v: f64) {
        for iy in 0..self.grid_shape().1 {
            let y = self.point(0, iy)[1];
            if y < y0 - 1e-9 || y > y1 + 1e-9 {
                continue;
            }
            for ix in self.columns(x0, x1) {
                self.set(ix, iy, z, v);
            }
        }
    }

    /// Sets sample (ix, iy) to `z` m quantised to `v` m.
    fn set(&mut self, ix: usize, iy: usize, z: f64, v: f64) {
        self.field.set_height_m(ix, iy, (z / v).round() * v);
    }

    /// The height grid (shared implementation with the training terrain).
    pub fn heightfield(&self) -> &Heightfield {
        &self.field
    }
    /// World (x, y) of sample (ix, iy).
    pub fn point(&self, ix: usize, iy: usize) -> [f64; 2] {
        self.field.point_m(ix, iy)
    }
    /// (samples along x, samples along y).
    pub fn grid_shape(&self) -> (usize, usize) {
        self.field.grid_shape()
    }
    /// World (x, y) of sample (0, 0).
    pub fn grid_origin_m(&self) -> [f64; 2] {
        self.field.grid_origin_m()
    }
    /// Spacing between samples, m.
    pub fn horizontal_scale_m(&self) -> f64 {
        self.field.horizontal_scale_m()
    }
    /// Heights (m), `heights_m()[iy * nx + ix]`.
    pub fn heights_m(&self) -> &[f32] {
        self.field.heights_m()
    }
    /// The race course's stretches (empty for other grounds).
    pub fn segments(&self) -> &[Segment] {
        &self.segments
    }
    /// Lowest and highest ground, m.
    pub fn height_range_m(&self) -> (f64, f64) {
        self.field.height_range_m()
    }
    /// Ground height at world (x, y), m: see [`Heightfield::height_at`].
    pub fn height_at(&self, x: f64, y: f64) -> f64 {
        self.field.height_at(x, y)
    }

    /// `<asset>` and `<worldbody>` MJCF of this ground: the hfield geom
    /// [`GROUND_NAME`] and a plane under it.
    pub fn xml(&self) -> (String, String) {
        let n = GROUND_NAME;
        let (lo, _) = self.height_range_m();
        let asset = format!("    {}", self.field.asset_xml(n));
        let world = format!(
            "    {}\n    \
             <geom name=\"{n}_net\" type=\"plane\" size=\"0 0 0.05\" pos=\"0 0 {}\" {GROUND_ATTRS}/>",
            self.field.geom_xml(n, GROUND_ATTRS),
            lo - NET_DEPTH_M
        );
        (asset, world)
    }

    /// Writes the heights into the model's hfield [`GROUND_NAME`]; refuses a
    /// model whose hfield does not have this ground's shape and size.
    pub fn upload(&self, model: &mut Model) -> Result<(), String> {
        self.field.upload(model, GROUND_NAME)
    }
}

/// `<worldbody>` MJCF of a flat plane named [`GROUND_NAME`] at z = 0.
pub fn plane_xml() -> String {
    format!("    <geom name=\"{GROUND_NAME}\" type=\"plane\" size=\"0 0 0.05\" {GROUND_ATTRS}/>")
}

/// `<worldbody>` MJCF of the platform box: top at z = `height_m`, front edge at
/// x = `edge_x_m`, reaching `length_m` back and `width_m` wide.
pub fn platform_xml(height_m: f64, edge_x_m: f64, length_m: f64, width_m: f64) -> String {
    format!(
        "    <geom name=\"platform\" type=\"box\" size=\"{} {} {}\" pos=\"{} 0 {}\" {GROUND_ATTRS}/>",
        length_m / 2.0,
        width_m / 2.0,
        height_m / 2.0,
        edge_x_m - length_m / 2.0,
        height_m / 2.0
    )
}

/// Uniform random heights on a lattice of about `lattice` m over a rectangle,
/// interpolated bilinearly.
struct LatticeNoise {
    lo: [f64; 2],
    step: [f64; 2],
    mx: usize,
    my: usize,
    values: Vec<f64>,
}

impl LatticeNoise {
    fn new(
        lo: [f64; 2],
        hi: [f64; 2],
        lattice: f64,
        amplitude: f64,
        v: f64,
        rng: &mut ChaCha8Rng,
    ) -> LatticeNoise {
        let k = (amplitude / v).round() as i64;
        let mx = (((hi[0] - lo[0]) / lattice).round() as usize).max(1) + 1;
        let my = (((hi[1] - lo[1]) / lattice).round() as usize).max(1) + 1;
        let values = (0..mx * my)
            .map(|_| rng.gen_range(-k..=k) as f64 * v)
            .collect();
        LatticeNoise {
            lo,
            step: [
                (hi[0] - lo[0]) / (mx - 1) as f64,
                (hi[1] - lo[1]) / (my - 1) as f64,
            ],
            mx,
            my,
            values,
        }
    }

    fn at(&self, x: f64, y: f64) -> f64 {
        let fx = ((x - self.lo[0]) / self.step[0]).clamp(0.0, (self.mx - 1) as f64);
        let fy = ((y - self.lo[1]) / self.step[1]).clamp(0.0, (self.my - 1) as f64);
        let i = (fx.floor() as usize).min(self.mx - 2);
        let j = (fy.floor() as usize).min(self.my - 2);
        let (tx, ty) = (fx - i as f64, fy - j as f64);
        let g = |i: usize, j: usize| self.values[j * self.mx + i];
        (1.0 - ty) * ((1.0 - tx) * g(i, j) + tx * g(i + 1, j))
            + ty * ((1.0 - tx) * g(i, j + 1) + tx * g(i + 1, j + 1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rough_ground_has_a_flat_pad_and_bounded_noise() {
        let p = RoughParams {
            half_extent_m: 5.0,
            ..Default::default()
        };
        let g = Ground::rough(&p, 3);
        assert_eq!(g.height_at(0.0, 0.0), 0.0);
        assert_eq!(g.height_at(0.5, -0.5), 0.0);
        let (lo, hi) = g.height_range_m();
        assert!(lo >= -p.amplitude_m - 1e-6 && hi <= p.amplitude_m + 1e-6);
        assert!(hi - lo > p.amplitude_m, "noise spans {lo}..{hi}");
        assert_eq!(
            Ground::rough(&p, 3).heights_m(),
            g.heights_m(),
            "deterministic"
        );
    }

    #[test]
    fn race_track_starts_on_the_platform_and_drops() {
        let p = RaceTrackParams::default();
        let g = Ground::race_track(&p, 0);
        let seg = g.segments();
        assert_eq!(seg[0].kind, SegmentKind::Platform);
        assert!((g.height_at(0.0, 0.0) - p.drop_height_m).abs() < 1e-6);
        let edge = seg[0].x1_m;
        assert!(g.height_at(edge + 0.5, 0.0).abs() < 1e-6);
        assert!(seg.iter().any(|s| s.kind == SegmentKind::Obstacles));
        assert!(seg.iter().any(|s| s.kind == SegmentKind::Rough));
    }
}
