//! One MuJoCo heightfield as plain data: the height grid shared by the training
//! terrain (`env::terrain`) and the evaluation ground (`eval::ground`).
//!
//! Heights are in metres, row-major with the row index along y and the column
//! index along x: exactly MuJoCo's hfield layout (`data[r * ncol + c]` is the
//! point x = -rx + c dx, y = -ry + r dy relative to the geom position), so
//! [`Heightfield::upload`] is a plain rescale. Sample (ix, iy) lies at world
//! `origin + (ix h, iy h)`.

use std::sync::OnceLock;

use crate::sim::{Model, ObjKind};

/// How a grid becomes a MuJoCo hfield: the block under it and its vertical range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HfieldSpec {
    /// Depth of the solid block under the surface (MuJoCo's hfield `base_z`), m.
    pub base_m: f64,
    /// Smallest hfield elevation (`size[2]`), used when the grid is (nearly) flat, m.
    pub min_elevation_m: f64,
    /// Whether z = 0 always lies within [`Heightfield::height_range_m`] (the
    /// training terrain's flat border), rather than only the samples' own range.
    pub range_spans_zero: bool,
}

/// A height grid with its placement in the world and its MuJoCo hfield form.
#[derive(Debug, Clone)]
pub struct Heightfield {
    origin_m: [f64; 2],
    horizontal_scale_m: f64,
    nx: usize,
    ny: usize,
    heights_m: Vec<f32>,
    spec: HfieldSpec,
    /// (lowest, highest) height, computed on first use and cleared by edits.
    range_m: OnceLock<(f64, f64)>,
}

impl Heightfield {
    /// A grid of `nx x ny` samples `horizontal_scale_m` apart, sample (0, 0) at
    /// `origin_m`, heights `heights_m[iy * nx + ix]`. Panics on fewer than 2 x 2
    /// samples, a non-positive spacing or a height count other than nx ny.
    pub fn new(
        origin_m: [f64; 2],
        horizontal_scale_m: f64,
        (nx, ny): (usize, usize),
        heights_m: Vec<f32>,
        spec: HfieldSpec,
    ) -> Heightfield {
        assert!(
            nx >= 2 && ny >= 2 && horizontal_scale_m > 0.0,
            "a heightfield needs 2 x 2 samples"
        );
        assert_eq!(heights_m.len(), nx * ny, "heights for {nx} x {ny} samples");
        Heightfield {
            origin_m,
            horizontal_scale_m,
            nx,
            ny,
            heights_m,
            spec,
            range_m: OnceLock::new(),
        }
    }

    /// A grid of `nx x ny` samples at height 0 (see [`Heightfield::new`]).
    pub fn flat(
        origin_m: [f64; 2],
        horizontal_scale_m: f64,
        (nx, ny): (usize, usize),
        spec: HfieldSpec,
    ) -> Heightfield {
        let heights_m = vec![0.0; nx * ny];
        Heightfield::new(origin_m, horizontal_scale_m, (nx, ny), heights_m, spec)
    }

    /// Samples along x (hfield columns) and along y (hfield rows).
    pub fn grid_shape(&self) -> (usize, usize) {
        (self.nx, self.ny)
    }
    /// World (x, y) of sample (0, 0), m.
    pub fn grid_origin_m(&self) -> [f64; 2] {
        self.origin_m
    }
    /// Spacing between samples, m.
    pub fn horizontal_scale_m(&self) -> f64 {
        self.horizontal_scale_m
    }
    /// Heights in metres, row-major, `heights_m()[iy * nx + ix]`.
    pub fn heights_m(&self) -> &[f32] {
        &self.heights_m
    }
    /// The hfield settings this grid was built with.
    pub fn spec(&self) -> &HfieldSpec {
        &self.spec
    }

    /// World (x, y) of sample (ix, iy), m.
    pub fn point_m(&self, ix: usize, iy: usize) -> [f64; 2] {
        [
            self.origin_m[0] + ix as f64 * self.horizontal_scale_m,
            self.origin_m[1] + iy as f64 * self.horizontal_scale_m,
        ]
    }

    /// Height of sample (ix, iy), m.
    pub fn sample_height_m(&self, ix: usize, iy: usize) -> f64 {
        self.heights_m[iy * self.nx + ix] as f64
    }

    /// Sets sample (ix, iy) to `z_m` (stored as f32).
    pub fn set_height_m(&mut self, ix: usize, iy: usize, z_m: f64) {
        self.heights_m[iy * self.nx + ix] = z_m as f32;
        self.range_m = OnceLock::new();
    }

    /// Lowest and highest ground, m (z = 0 included if the spec says so).
    pub fn height_range_m(&self) -> (f64, f64) {
        *self.range_m.get_or_init(|| self.scan_range_m())
    }

    /// Folds every sample into (lowest, highest), m.
    fn scan_range_m(&self) -> (f64, f64) {
        let start = if self.spec.range_spans_zero {
            (0.0f64, 0.0f64)
        } else {
            (f64::INFINITY, f64::NEG_INFINITY)
        };
        self.heights_m
            .iter()
            .fold(start, |(lo, hi), &z| (lo.min(z as f64), hi.max(z as f64)))
    }

    /// Ground height at world (x, y), bilinear between samples; points outside
    /// the grid take the nearest edge value (there is no ground there in MuJoCo).
    /// MuJoCo triangulates each cell instead; the two agree on planar patches.
    pub fn height_at(&self, x_m: f64, y_m: f64) -> f64 {
        let [x0, y0] = self.origin_m;
        let h = self.horizontal_scale_m;
        let fx = ((x_m - x0) / h).clamp(0.0, (self.nx - 1) as f64);
        let fy = ((y_m - y0) / h).clamp(0.0, (self.ny - 1) as f64);
        let ix = (fx.floor() as usize).min(self.nx - 2);
        let iy = (fy.floor() as usize).min(self.ny - 2);
        let (tx, ty) = (fx - ix as f64, fy - iy as f64);
        let z = |i: usize, j: usize| self.sample_height_m(i, j);
        (1.0 - ty) * ((1.0 - tx) * z(ix, iy) + tx * z(ix + 1, iy))
            + ty * ((1.0 - tx) * z(ix, iy + 1) + tx * z(ix + 1, iy + 1))
    }

    /// (radius_x, radius_y, elevation, base) of the MuJoCo hfield, m.
    pub fn hfield_size_m(&self) -> [f64; 4] {
        let (lo, hi) = self.height_range_m();
        let h = self.horizontal_scale_m;
        [
            (self.nx - 1) as f64 * h / 2.0,
            (self.ny - 1) as f64 * h / 2.0,
            (hi - lo).max(self.spec.min_elevation_m),
            self.spec.base_m,
        ]
    }

    /// World position of the hfield geom (grid centre, z = lowest ground), m.
    pub fn hfield_pos_m(&self) -> [f64; 3] {
        let [x0, y0] = self.origin_m;
        let [rx, ry, _, _] = self.hfield_size_m();
        [x0 + rx, y0 + ry, self.height_range_m().0]
    }

    /// The `<hfield>` asset element named `name` (one line, no indentation).
    pub fn asset_xml(&self, name: &str) -> String {
        let [rx, ry, elev, base] = self.hfield_size_m();
        let (nrow, ncol) = (self.ny, self.nx);
        format!(
            "<hfield name=\"{name}\" nrow=\"{nrow}\" ncol=\"{ncol}\" \
             size=\"{rx} {ry} {elev} {base}\"/>"
        )
    }

    /// The `<geom>` element named `name` showing hfield `name`, with the extra
    /// attributes `attrs` (one line, no indentation).
    pub fn geom_xml(&self, name: &str, attrs: &str) -> String {
        let [px, py, pz] = self.hfield_pos_m();
        format!(
            "<geom name=\"{name}\" type=\"hfield\" hfield=\"{name}\" pos=\"{px} {py} {pz}\" \
             {attrs}/>"
        )
    }

    /// Writes the heights into the model's hfield `name` as fractions of its
    /// elevation above the geom. Refuses a model without that hfield, or whose
    /// hfield does not have this grid's shape and size.
    pub fn upload(&self, model: &mut Model, name: &str) -> Result<(), String> {
        let hf = model
            .id(ObjKind::Hfield, name)
            .ok_or_else(|| format!("the model has no heightfield named \"{name}\""))?;
        self.check_hfield(model, hf, name)?;
        let (lo, _) = self.height_range_m();
        let elevation_m = self.hfield_size_m()[2];
        for (dst, &z) in model.hfield_data_mut(hf).iter_mut().zip(&self.heights_m) {
            *dst = ((z as f64 - lo) / elevation_m).clamp(0.0, 1.0) as f32;
        }
        Ok(())
    }

    /// Whether hfield `hf` (named `name`) has this grid's shape and size.
    fn check_hfield(&self, model: &Model, hf: usize, name: &str) -> Result<(), String> {
        let shape = model.hfield_shape(hf);
        if shape != (self.ny, self.nx) {
            return Err(format!(
                "heightfield \"{name}\" has {} x {} samples (rows x cols), the grid {} x {}",
                shape.0, shape.1, self.ny, self.nx
            ));
        }
        let want = self.hfield_size_m();
        let got = model.hfield_size(hf);
        if want
            .iter()
            .zip(got.iter())
            .any(|(w, g)| (w - g).abs() > 1e-9 * w.abs().max(1.0))
        {
            return Err(format!(
                "heightfield \"{name}\" has size {got:?}, the grid {want:?}"
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SPEC: HfieldSpec = HfieldSpec {
        base_m: 0.5,
        min_elevation_m: 0.001,
        range_spans_zero: false,
    };

    /// 3 x 2 samples 0.5 m apart from (1, 2), heights 1..=6 cm.
    fn grid(spec: HfieldSpec) -> Heightfield {
        let z = vec![0.01, 0.02, 0.03, 0.04, 0.05, 0.06];
        Heightfield::new([1.0, 2.0], 0.5, (3, 2), z, spec)
    }

    #[test]
    fn range_spans_zero_only_when_asked_and_follows_edits() {
        let mut g = grid(SPEC);
        assert_eq!(g.height_range_m(), (0.01f32 as f64, 0.06f32 as f64));
        let spanning = HfieldSpec {
            range_spans_zero: true,
            ..SPEC
        };
        assert_eq!(grid(spanning).height_range_m(), (0.0, 0.06f32 as f64));
        g.set_height_m(2, 1, -0.2);
        assert_eq!(g.height_range_m(), (-0.2f32 as f64, 0.05f32 as f64));
        assert_eq!(g.sample_height_m(2, 1), -0.2f32 as f64);
    }

    #[test]
    fn height_at_interpolates_and_clamps_to_the_edges() {
        let g = grid(SPEC);
        assert_eq!(g.point_m(2, 1), [2.0, 2.5]);
        assert_eq!(g.height_at(1.0, 2.0), 0.01f32 as f64);
        let mid = g.height_at(1.25, 2.25);
        let want = (0.01f32 as f64 + 0.02f32 as f64 + 0.04f32 as f64 + 0.05f32 as f64) / 4.0;
        assert!((mid - want).abs() < 1e-12, "{mid} vs {want}");
        assert_eq!(g.height_at(9.0, 9.0), 0.06f32 as f64);
        assert_eq!(g.height_at(-9.0, -9.0), 0.01f32 as f64);
    }

    #[test]
    fn hfield_text_places_the_grid_centre_at_the_lowest_ground() {
        let g = Heightfield::flat([-1.0, 0.0], 0.5, (5, 3), SPEC);
        assert_eq!(g.hfield_size_m(), [1.0, 0.5, 0.001, 0.5]);
        assert_eq!(g.hfield_pos_m(), [0.0, 0.5, 0.0]);
        assert_eq!(
            g.asset_xml("g"),
            "<hfield name=\"g\" nrow=\"3\" ncol=\"5\" size=\"1 0.5 0.001 0.5\"/>"
        );
        assert_eq!(
            g.geom_xml("g", "rgba=\"1 1 1 1\""),
            "<geom name=\"g\" type=\"hfield\" hfield=\"g\" pos=\"0 0.5 0\" rgba=\"1 1 1 1\"/>"
        );
    }

    #[test]
    fn upload_writes_fractions_and_refuses_other_hfields() {
        let g = grid(SPEC);
        let xml = |field: &Heightfield| {
            format!(
                "<mujoco><asset>{}</asset><worldbody>{}</worldbody></mujoco>",
                field.asset_xml("hf"),
                field.geom_xml("hf", "")
            )
        };
        let mut model = Model::from_xml_str(&xml(&g), "grid").unwrap();
        g.upload(&mut model, "hf").unwrap();
        let hf = model.id(ObjKind::Hfield, "hf").unwrap();
        let data = model.hfield_data(hf);
        assert_eq!((data[0], data[5]), (0.0, 1.0));
        assert!(g.upload(&mut model, "other").unwrap_err().contains("other"));
        let wider = Heightfield::flat([1.0, 2.0], 0.5, (4, 2), SPEC);
        assert!(wider.upload(&mut model, "hf").is_err());
        let coarser = Heightfield::new([1.0, 2.0], 1.0, (3, 2), g.heights_m().to_vec(), SPEC);
        assert!(coarser
            .upload(&mut model, "hf")
            .unwrap_err()
            .contains("size"));
    }
}
