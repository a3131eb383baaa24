//! legged_gym-style terrain: a grid of heightfield tiles (rows = difficulty levels
//! along x, columns = terrain types along y) and the level curriculum, as plain data.
//!
//! World layout (as legged_gym): tile (level `i`, type `j`) covers
//! x in [i L, (i+1) L), y in [j W, (j+1) W); a flat border of `border_size_m`
//! surrounds the whole grid, so the heightfield spans
//! [-border, levels L + border] x [-border, types W + border].
//!
//! Heights are stored in metres, quantised to `vertical_scale_m`, row-major with
//! the row index along y and the column index along x: exactly MuJoCo's hfield
//! layout (`data[r * ncol + c]` is the point x = -rx + c dx, y = -ry + r dy
//! relative to the geom position), so [`Terrain::upload`] is a plain rescale.
//! The grid itself is a [`Heightfield`], shared with the evaluation ground.
//!
//! Tile types follow legged_gym's `terrain.py` in spirit (not its code):
//! - smooth slope: a pyramid of slope 0.4 d with a flat central platform; the
//!   first half of the smooth-slope columns are inverted (pits, the robot climbs
//!   out), the second half are pyramids (the robot walks down), as legged_gym;
//! - rough slope: a pyramid of slope 0.4 d plus uniform noise of
//!   +-(0.025 + 0.075 d) on a 0.2 m lattice, bilinearly interpolated, outside the platform;
//! - stairs up / down: concentric steps of 0.05 + 0.18 d m every 0.31 m
//!   ("up": a stair pit the robot climbs out of; "down": a stair pyramid);
//! - discrete obstacles: 20 rectangles of 1 to 2 m with heights
//!   +-h, +-h/2, h = 0.05 + 0.2 d;
//! - flat.
//!
//! with d = level / num_levels. Every tile keeps a flat central platform
//! (`platform_size_m`), where robots spawn ([`Terrain::tile_origin`]).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::heightfield::{Heightfield, HfieldSpec};
use crate::sim::Model;

/// Name of the ground geom (and of the hfield asset) that [`Terrain::scene_xml`] adds.
pub const TERRAIN_NAME: &str = "terrain";

/// Depth of the solid box under the heightfield (MuJoCo's hfield `base_z`), m.
const HFIELD_BASE_M: f64 = 1.0;
/// Largest grid [`TerrainConfig::validate`] accepts (samples), about 200 MB of f32.
const MAX_SAMPLES: usize = 50_000_000;

// legged_gym's per-type constants.
const SLOPE_PER_DIFFICULTY: f64 = 0.4;
const ROUGH_NOISE_BASE_M: f64 = 0.025;
const ROUGH_NOISE_PER_DIFFICULTY_M: f64 = 0.075;
const ROUGH_NOISE_LATTICE_M: f64 = 0.2;
const STEP_WIDTH_M: f64 = 0.31;
const STEP_HEIGHT_BASE_M: f64 = 0.05;
const STEP_HEIGHT_PER_DIFFICULTY_M: f64 = 0.18;
const OBSTACLE_HEIGHT_BASE_M: f64 = 0.05;
const OBSTACLE_HEIGHT_PER_DIFFICULTY_M: f64 = 0.2;
const OBSTACLE_COUNT: usize = 20;
const OBSTACLE_MIN_SIZE_M: f64 = 1.0;
const OBSTACLE_MAX_SIZE_M: f64 = 2.0;
const OBSTACLE_GRID_M: f64 = 0.4;
/// Separates the curriculum's random streams from the terrain's.
const CURRICULUM_SALT: u64 = 0x6375_7272_6963_756c;
/// Half-size of the central square whose highest point sets a tile's spawn height.
const SPAWN_HALF_SIZE_M: f64 = 1.0;

/// Flat ground (a plane) or the tiled heightfield.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TerrainKind {
    Flat,
    #[default]
    Rough,
}

/// Share of the terrain-type columns given to each tile type: each in [0, 1],
/// summing to 1.
/// Columns are assigned in this field order (legged_gym's order, then flat).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TerrainProportions {
    pub smooth_slope: f64,
    pub rough_slope: f64,
    pub stairs_up: f64,
    pub stairs_down: f64,
    pub discrete: f64,
    pub flat: f64,
}

impl Default for TerrainProportions {
    /// RALL trains on smooth slopes, rough slopes and discrete obstacles (no
    /// stairs); legged_gym's own mix is [0.1, 0.1, 0.35, 0.25, 0.2].
    fn default() -> Self {
        TerrainProportions {
            smooth_slope: 0.3,
            rough_slope: 0.3,
            stairs_up: 0.0,
            stairs_down: 0.0,
            discrete: 0.3,
            flat: 0.1,
        }
    }
}

impl TerrainProportions {
    fn entries(&self) -> [(&'static str, f64); 6] {
        [
            ("smooth_slope", self.smooth_slope),
            ("rough_slope", self.rough_slope),
            ("stairs_up", self.stairs_up),
            ("stairs_down", self.stairs_down),
            ("discrete", self.discrete),
            ("flat", self.flat),
        ]
    }
}

/// Terrain layout and curriculum settings (legged_gym's defaults unless noted).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TerrainConfig {
    pub kind: TerrainKind,
    /// Tile extent along x (the level axis), m: in (0, 100], a multiple of
    /// `horizontal_scale_m` spanning at least 4 samples.
    pub tile_length_m: f64,
    /// Tile extent along y (the type axis), m: as `tile_length_m`.
    pub tile_width_m: f64,
    /// Rows: difficulty levels, along x; 1..=1000.
    pub num_levels: usize,
    /// Columns: terrain types, along y; 1..=1000.
    pub num_types: usize,
    /// Heightfield sample spacing, m, in [0.01, 1].
    pub horizontal_scale_m: f64,
    /// Height quantum, m, in (0, 0.025]: heights are rounded to it, so a coarser
    /// quantum rounds the smallest features away (the rough slopes' noise of
    /// +-0.025 m at level 0; 1e30 makes every tile flat).
    pub vertical_scale_m: f64,
    /// Flat margin around the tile grid, m, in [0, 100] and a multiple of
    /// `horizontal_scale_m`. legged_gym uses 25 m; 5 m here keeps
    /// the default grid at 901 x 1701 samples (6 MB of f32 per model copy).
    pub border_size_m: f64,
    /// Side of the flat central square of every tile, m, in [0, the tile's shorter side].
    pub platform_size_m: f64,
    /// Initial curriculum levels are drawn uniformly from [0, max_init_level];
    /// below `num_levels`.
    pub max_init_level: usize,
    pub proportions: TerrainProportions,
}

impl Default for TerrainConfig {
    fn default() -> Self {
        TerrainConfig {
            kind: TerrainKind::Rough,
            tile_length_m: 8.0,
            tile_width_m: 8.0,
            num_levels: 10,
            num_types: 20,
            horizontal_scale_m: 0.1,
            vertical_scale_m: 0.005,
            border_size_m: 5.0,
            platform_size_m: 3.0,
            max_init_level: 5,
            proportions: TerrainProportions::default(),
        }
    }
}

/// The most difficulty levels (and terrain types) a terrain may have.
pub const MAX_TERRAIN_LEVELS: usize = 1000;
/// The coarsest height quantum (m): the rough slopes' noise at level 0.
pub const MAX_VERTICAL_SCALE_M: f64 = ROUGH_NOISE_BASE_M;
/// The largest tile side or border (m).
const MAX_EXTENT_M: f64 = 100.0;

/// Whether `v` is a whole number of `step`s (to 1e-6 relative).
fn is_multiple(v: f64, step: f64) -> bool {
    let k = (v / step).round();
    (v - k * step).abs() <= 1e-6 * step.max(v.abs())
}

impl TerrainConfig {
    /// Checks every value; the error names the offending key (`terrain.<key>`).
    pub fn validate(&self) -> Result<(), String> {
        let positive = |key: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(format!(
                    "terrain.{key} must be a positive number of metres, got {v}"
                ))
            }
        };
        positive("horizontal_scale_m", self.horizontal_scale_m)?;
        positive("vertical_scale_m", self.vertical_scale_m)?;
        positive("tile_length_m", self.tile_length_m)?;
        positive("tile_width_m", self.tile_width_m)?;
        for (key, v, lo, hi) in [
            ("horizontal_scale_m", self.horizontal_scale_m, 0.01, 1.0),
            (
                "vertical_scale_m",
                self.vertical_scale_m,
                0.0,
                MAX_VERTICAL_SCALE_M,
            ),
            ("tile_length_m", self.tile_length_m, 0.0, MAX_EXTENT_M),
            ("tile_width_m", self.tile_width_m, 0.0, MAX_EXTENT_M),
            ("border_size_m", self.border_size_m, 0.0, MAX_EXTENT_M),
        ] {
            if !(lo..=hi).contains(&v) {
                return Err(format!(
                    "terrain.{key} must be in [{lo}, {hi}] m, got {v}{}",
                    if key == "vertical_scale_m" {
                        ": heights are rounded to it, and a coarser quantum rounds the terrain's features away"
                    } else {
                        ""
                    }
                ));
            }
        }
        let h = self.horizontal_scale_m;
        for (key, v) in [
            ("tile_length_m", self.tile_length_m),
            ("tile_width_m", self.tile_width_m),
        ] {
            if !is_multiple(v, h) {
                return Err(format!(
                    "terrain.{key} = {v} is not a multiple of terrain.horizontal_scale_m = {h}"
                ));
            }
            if v < 4.0 * h {
                return Err(format!(
                    "terrain.{key} = {v} spans fewer than 4 samples of {h} m"
                ));
            }
        }
        if !(self.border_size_m.is_finite() && self.border_size_m >= 0.0) {
            return Err(format!(
                "terrain.border_size_m must be >= 0, got {}",
                self.border_size_m
            ));
        }
        if !is_multiple(self.border_size_m, h) {
            return Err(format!(
                "terrain.border_size_m = {} is not a multiple of terrain.horizontal_scale_m = {h}",
                self.border_size_m
            ));
        }
        let min_side = self.tile_length_m.min(self.tile_width_m);
        if !(self.platform_size_m.is_finite()
            && self.platform_size_m >= 0.0
            && self.platform_size_m <= min_side)
        {
            return Err(format!(
                "terrain.platform_size_m must be in [0, {min_side}] (the tile side), got {}",
                self.platform_size_m
            ));
        }
        if self.num_levels == 0 {
            return Err("terrain.num_levels must be at least 1".into());
        }
        if self.num_types == 0 {
            return Err("terrain.num_types must be at least 1".into());
        }
        if self.max_init_level >= self.num_levels {
            return Err(format!(
                "terrain.max_init_level = {} must be below terrain.num_levels = {}",
                self.max_init_level, self.num_levels
            ));
        }
        let mut sum = 0.0;
        for (key, v) in self.proportions.entries() {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("terrain.proportions.{key} must be >= 0, got {v}"));
            }
            sum += v;
        }
        if (sum - 1.0).abs() > 1e-6 {
            return Err(format!("terrain.proportions must sum to 1, got {sum}"));
        }
        let (nx, ny) = self.grid_samples();
        if nx.saturating_mul(ny) > MAX_SAMPLES {
            return Err(format!(
                "terrain grid of {nx} x {ny} samples is too large (limit {MAX_SAMPLES}): \
                 reduce terrain.num_levels, terrain.num_types or the tile size, \
                 or raise terrain.horizontal_scale_m"
            ));
        }
        for (key, n) in [
            ("num_levels", self.num_levels),
            ("num_types", self.num_types),
        ] {
            if n > MAX_TERRAIN_LEVELS {
                return Err(format!(
                    "terrain.{key} must be at most {MAX_TERRAIN_LEVELS}, got {n}"
                ));
            }
        }
        Ok(())
    }

    fn samples(&self, metres: f64) -> usize {
        (metres / self.horizontal_scale_m).round() as usize
    }

    /// (along x, along y) sample counts of the whole grid, border included.
    fn grid_samples(&self) -> (usize, usize) {
        let b = self.samples(self.border_size_m);
        let side = |n: usize, tile: f64| {
            n.saturating_mul(self.samples(tile))
                .saturating_add(2 * b + 1)
        };
        (
            side(self.num_levels, self.tile_length_m),
            side(self.num_types, self.tile_width_m),
        )
    }

    /// The tile type of column `col` (legged_gym: choice = col / num_types + 0.001
    /// against the cumulative proportions).
    fn kind_of_column(&self, col: usize) -> TileKind {
        if self.kind == TerrainKind::Flat {
            return TileKind::Flat;
        }
        let choice = col as f64 / self.num_types as f64 + 0.001;
        let p = &self.proportions;
        let mut cum = 0.0;
        let mut last = TileKind::Flat;
        for (i, (_, share)) in p.entries().into_iter().enumerate() {
            if share <= 0.0 {
                continue;
            }
            let start = cum;
            cum += share;
            let kind = match i {
                0 if choice < start + share / 2.0 => TileKind::SlopePit,
                0 => TileKind::SlopePyramid,
                1 => TileKind::RoughSlope,
                2 => TileKind::StairsUp,
                3 => TileKind::StairsDown,
                4 => TileKind::Discrete,
                _ => TileKind::Flat,
            };
            if choice < cum {
                return kind;
            }
            last = kind;
        }
        last
    }
}

/// What a terrain-type column holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TileKind {
    /// Inverted smooth pyramid: the platform is the lowest point (walk uphill out).
    SlopePit,
    /// Smooth pyramid: the platform is the highest point (walk downhill out).
    SlopePyramid,
    /// Pyramid with uniform noise outside the platform.
    RoughSlope,
    /// Stair pit: the platform is the lowest step (climb up out).
    StairsUp,
    /// Stair pyramid: the platform is the highest step (walk down out).
    StairsDown,
    /// Random rectangular blocks and holes.
    Discrete,
    Flat,
}

/// A generated terrain: the height grid, tile kinds and spawn origins.
#[derive(Debug, Clone)]
pub struct Terrain {
    cfg: TerrainConfig,
    seed: u64,
    /// The height grid, sample (0, 0) at (-border, -border).
    field: Heightfield,
    kinds: Vec<TileKind>,
    /// level * num_types + type -> spawn point.
    origins: Vec<[f64; 3]>,
}

/// One tile under construction: heights in metres, index `b * nl + a`
/// (a along x, b along y).
struct Tile {
    nl: usize,
    nw: usize,
    h: f64,
    z: Vec<f64>,
}

impl Tile {
    fn new(nl: usize, nw: usize, h: f64) -> Tile {
        Tile {
            nl,
            nw,
            h,
            z: vec![0.0; nl * nw],
        }
    }
    fn at(&mut self, a: usize, b: usize) -> &mut f64 {
        &mut self.z[b * self.nl + a]
    }
    /// Whether sample (a, b) lies on the central platform of side `p` metres.
    fn in_platform(&self, a: usize, b: usize, p: f64) -> bool {
        let dx = (a as f64 * self.h - self.nl as f64 * self.h / 2.0).abs();
        let dy = (b as f64 * self.h - self.nw as f64 * self.h / 2.0).abs();
        dx <= p / 2.0 + 1e-9 && dy <= p / 2.0 + 1e-9
    }

    /// A true pyramid (four planar faces of slope `slope`, negative for a pit)
    /// clipped to a flat central platform of side `p`.
    fn pyramid(&mut self, slope: f64, p: f64) {
        let half = (self.nl.min(self.nw) as f64 * self.h) / 2.0;
        let cap = slope.abs() * (half - p / 2.0).max(0.0);
        for b in 0..self.nw {
            for a in 0..self.nl {
                let ex = a.min(self.nl - a) as f64 * self.h;
                let ey = b.min(self.nw - b) as f64 * self.h;
                let rise = (slope.abs() * ex.min(ey)).min(cap);
                *self.at(a, b) += rise * slope.signum();
            }
        }
    }

    /// Uniform noise in [-amp, amp] (multiples of `v`) on a lattice of about
    /// `lattice` metres, bilinearly interpolated, added outside the platform.
    fn noise(&mut self, amp: f64, v: f64, lattice: f64, p: f64, rng: &mut ChaCha8Rng) {
        let k = (amp / v).round() as i64;
        let len = self.nl as f64 * self.h;
        let wid = self.nw as f64 * self.h;
        let mx = ((len / lattice).round() as usize).max(1) + 1;
        let my = ((wid / lattice).round() as usize).max(1) + 1;
        let lat: Vec<f64> = (0..mx * my)
            .map(|_| rng.gen_range(-k..=k) as f64 * v)
            .collect();
        let (sx, sy) = (len / (mx - 1) as f64, wid / (my - 1) as f64);
        for b in 0..self.nw {
            for a in 0..self.nl {
                if self.in_platform(a, b, p) {
                    continue;
                }
                let fx = a as f64 * self.h / sx;
                let fy = b as f64 * self.h / sy;
                let (i0, j0) = (
                    (fx.floor() as usize).min(mx - 2),
                    (fy.floor() as usize).min(my - 2),
                );
                let (tx, ty) = (fx - i0 as f64, fy - j0 as f64);
                let g = |i: usize, j: usize| lat[j * mx + i];
                let n = (1.0 - ty) * ((1.0 - tx) * g(i0, j0) + tx * g(i0 + 1, j0))
                    + ty * ((1.0 - tx) * g(i0, j0 + 1) + tx * g(i0 + 1, j0 + 1));
                *self.at(a, b) += n;
            }
        }
    }

    /// Concentric steps of `step_h` every `step_w` metres until the inner square
    /// is no larger than the platform (legged_gym's pyramid stairs).
    fn stairs(&mut self, step_w: f64, step_h: f64, p: f64) {
        let sw = ((step_w / self.h) as usize).max(1);
        let pp = (p / self.h) as usize;
        let (mut x0, mut x1, mut y0, mut y1) = (0usize, self.nl, 0usize, self.nw);
        let mut z = 0.0;
        while x1 - x0 > pp && y1 - y0 > pp && x1 - x0 > 2 * sw && y1 - y0 > 2 * sw {
            x0 += sw;
            x1 -= sw;
            y0 += sw;
            y1 -= sw;
            z += step_h;
            for b in y0..y1 {
                for a in x0..x1 {
                    *self.at(a, b) = z;
                }
            }
        }
    }

    /// `count` random rectangles at heights +-h, +-h/2, then a cleared platform.
    fn obstacles(&mut self, height: f64, v: f64, p: f64, rng: &mut ChaCha8Rng) {
        let k = (height / v).round() as i64;
        let levels = [-k, -(k / 2), k / 2, k];
        let grid = ((OBSTACLE_GRID_M / self.h).round() as usize).max(1);
        let min_s = ((OBSTACLE_MIN_SIZE_M / self.h) as usize).max(1);
        let max_s = ((OBSTACLE_MAX_SIZE_M / self.h) as usize).max(min_s + 1);
        let sizes: Vec<usize> = (min_s..max_s).step_by(grid).collect();
        for _ in 0..OBSTACLE_COUNT {
            let w = sizes[rng.gen_range(0..sizes.len())].min(self.nl - 1);
            let l = sizes[rng.gen_range(0..sizes.len())].min(self.nw - 1);
            let xs: Vec<usize> = (0..self.nl - w).step_by(grid).collect();
            let ys: Vec<usize> = (0..self.nw - l).step_by(grid).collect();
            let a0 = xs[rng.gen_range(0..xs.len())];
            let b0 = ys[rng.gen_range(0..ys.len())];
            let z = levels[rng.gen_range(0..levels.len())] as f64 * v;
            for b in b0..b0 + l {
                for a in a0..a0 + w {
                    *self.at(a, b) = z;
                }
            }
        }
        for b in 0..self.nw {
            for a in 0..self.nl {
                if self.in_platform(a, b, p) {
                    *self.at(a, b) = 0.0;
                }
            }
        }
    }
}

impl Terrain {
    /// Generates the terrain; deterministic in `seed` (each tile draws from its
    /// own ChaCha8 stream). Panics if `cfg` fails [`TerrainConfig::validate`].
    pub fn generate(cfg: &TerrainConfig, seed: u64) -> Terrain {
        if let Err(e) = cfg.validate() {
            panic!("invalid terrain config: {e}");
        }
        let (nx, ny) = cfg.grid_samples();
        let v = cfg.vertical_scale_m;
        let nl = cfg.samples(cfg.tile_length_m);
        let nw = cfg.samples(cfg.tile_width_m);
        let border = cfg.samples(cfg.border_size_m);
        let kinds: Vec<TileKind> = (0..cfg.num_types).map(|c| cfg.kind_of_column(c)).collect();
        let mut heights = vec![0.0f32; nx * ny];
        let mut origins = vec![[0.0; 3]; cfg.num_levels * cfg.num_types];
        let spawn = cfg.samples(SPAWN_HALF_SIZE_M).max(1);
        for level in 0..cfg.num_levels {
            let d = level as f64 / cfg.num_levels as f64;
            for (col, &kind) in kinds.iter().enumerate() {
                let index = level * cfg.num_types + col;
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                rng.set_stream(index as u64);
                let tile = make_tile(kind, d, cfg, nl, nw, &mut rng);
                let (ox, oy) = (border + level * nl, border + col * nw);
                let mut spawn_z = f64::NEG_INFINITY;
                for b in 0..nw {
                    for a in 0..nl {
                        let z = (tile.z[b * nl + a] / v).round() * v;
                        heights[(oy + b) * nx + ox + a] = z as f32;
                        if a.abs_diff(nl / 2) <= spawn && b.abs_diff(nw / 2) <= spawn {
                            spawn_z = spawn_z.max(z as f32 as f64);
                        }
                    }
                }
                let x = (level as f64 + 0.5) * cfg.tile_length_m;
                let y = (col as f64 + 0.5) * cfg.tile_width_m;
                origins[index] = [x, y, spawn_z];
            }
        }
        let b = cfg.border_size_m;
        let field = Heightfield::new(
            [-b, -b],
            cfg.horizontal_scale_m,
            (nx, ny),
            heights,
            spec(cfg),
        );
        Terrain {
            cfg: cfg.clone(),
            seed,
            field,
            kinds,
            origins,
        }
    }

    pub fn config(&self) -> &TerrainConfig {
        &self.cfg
    }
    pub fn seed(&self) -> u64 {
        self.seed
    }
    /// Difficulty levels (rows, along x).
    pub fn num_levels(&self) -> usize {
        self.cfg.num_levels
    }
    /// Terrain types (columns, along y).
    pub fn num_types(&self) -> usize {
        self.cfg.num_types
    }
    /// What column `terrain_type` holds.
    pub fn tile_kind(&self, terrain_type: usize) -> TileKind {
        self.kinds[terrain_type]
    }
    /// The height grid (shared implementation with the evaluation ground).
    pub fn heightfield(&self) -> &Heightfield {
        &self.field
    }
    /// Samples along x (hfield columns) and along y (hfield rows).
    pub fn grid_shape(&self) -> (usize, usize) {
        self.field.grid_shape()
    }
    /// World (x, y) of sample (0, 0): (-border, -border).
    pub fn grid_origin_m(&self) -> [f64; 2] {
        self.field.grid_origin_m()
    }
    /// Spacing between samples, m.
    pub fn horizontal_scale_m(&self) -> f64 {
        self.field.horizontal_scale_m()
    }
    /// Heights in metres, row-major, `heights_m()[iy * nx + ix]` at world
    /// (x0 + ix h, y0 + iy h) with (x0, y0) = [`Self::grid_origin_m`].
    pub fn heights_m(&self) -> &[f32] {
        self.field.heights_m()
    }
    /// Height of sample (ix, iy), m.
    pub fn sample_height_m(&self, ix: usize, iy: usize) -> f64 {
        self.field.sample_height_m(ix, iy)
    }
    /// Lowest and highest ground (the flat border's 0 included), m.
    pub fn height_range_m(&self) -> (f64, f64) {
        self.field.height_range_m()
    }
    /// Ground height at world (x, y), m: see [`Heightfield::height_at`].
    pub fn height_at(&self, x_m: f64, y_m: f64) -> f64 {
        self.field.height_at(x_m, y_m)
    }

    /// Spawn point of tile (level, type): its centre, z = the highest ground
    /// within 1 m of the centre (the flat platform's height).
    pub fn tile_origin(&self, level: usize, terrain_type: usize) -> [f64; 3] {
        assert!(
            level < self.cfg.num_levels && terrain_type < self.cfg.num_types,
            "tile ({level}, {terrain_type}) outside {} x {}",
            self.cfg.num_levels,
            self.cfg.num_types
        );
        self.origins[level * self.cfg.num_types + terrain_type]
    }

    /// The robot's MJCF text with the ground added before its final `</mujoco>`:
    /// an hfield asset and geom named [`TERRAIN_NAME`] (kind rough), or a plane
    /// geom of that name (kind flat). The ground has contype 0 / conaffinity 1.
    /// After loading, call [`Terrain::upload`] to fill in the heights.
    pub fn scene_xml(&self, robot_xml: &str) -> Result<String, String> {
        let end = robot_xml
            .rfind("</mujoco>")
            .ok_or_else(|| "robot MJCF has no closing </mujoco> tag".to_string())?;
        const N: &str = TERRAIN_NAME;
        let common = "contype=\"0\" conaffinity=\"1\" condim=\"3\" \
                      friction=\"1.0 0.005 0.0001\" rgba=\"0.55 0.5 0.45 1\"";
        let ground = match self.cfg.kind {
            TerrainKind::Flat => format!(
                "  <worldbody>\n    \
                 <geom name=\"{N}\" type=\"plane\" size=\"0 0 0.05\" {common}/>\n  \
                 </worldbody>\n"
            ),
            TerrainKind::Rough => format!(
                "  <asset>\n    {}\n  </asset>\n  <worldbody>\n    {}\n  </worldbody>\n",
                self.field.asset_xml(N),
                self.field.geom_xml(N, common)
            ),
        };
        Ok(format!(
            "{}{}{}",
            &robot_xml[..end],
            ground,
            &robot_xml[end..]
        ))
    }

    /// Writes the heights into the model's hfield [`TERRAIN_NAME`] (as fractions of
    /// its elevation above the geom). A no-op for kind flat. Refuses a model whose
    /// hfield does not have this terrain's shape and size.
    pub fn upload(&self, model: &mut Model) -> Result<(), String> {
        if self.cfg.kind == TerrainKind::Flat {
            return Ok(());
        }
        self.field.upload(model, TERRAIN_NAME)
    }
}

/// The hfield settings of `cfg`'s grid: a 1 m block, elevation at least one
/// height quantum, and a range that always spans the flat border's z = 0.
fn spec(cfg: &TerrainConfig) -> HfieldSpec {
    HfieldSpec {
        base_m: HFIELD_BASE_M,
        min_elevation_m: cfg.vertical_scale_m,
        range_spans_zero: true,
    }
}

fn make_tile(
    kind: TileKind,
    d: f64,
    cfg: &TerrainConfig,
    nl: usize,
    nw: usize,
    rng: &mut ChaCha8Rng,
) -> Tile {
    let mut tile = Tile::new(nl, nw, cfg.horizontal_scale_m);
    let p = cfg.platform_size_m;
    let v = cfg.vertical_scale_m;
    let slope = SLOPE_PER_DIFFICULTY * d;
    match kind {
        TileKind::SlopePit => tile.pyramid(-slope, p),
        TileKind::SlopePyramid => tile.pyramid(slope, p),
        TileKind::RoughSlope => {
            tile.pyramid(slope, p);
            let amp = ROUGH_NOISE_BASE_M + ROUGH_NOISE_PER_DIFFICULTY_M * d;
            tile.noise(amp, v, ROUGH_NOISE_LATTICE_M, p, rng);
        }
        TileKind::StairsUp | TileKind::StairsDown => {
            let step = STEP_HEIGHT_BASE_M + STEP_HEIGHT_PER_DIFFICULTY_M * d;
            let sign = if kind == TileKind::StairsUp {
                -1.0
            } else {
                1.0
            };
            tile.stairs(STEP_WIDTH_M, sign * step, p);
        }
        TileKind::Discrete => {
            let height = OBSTACLE_HEIGHT_BASE_M + OBSTACLE_HEIGHT_PER_DIFFICULTY_M * d;
            tile.obstacles(height, v, p, rng);
        }
        TileKind::Flat => {}
    }
    tile
}

/// What [`Curriculum::update`] did to an env's level.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LevelChange {
    Promoted,
    Demoted,
    Unchanged,
    /// Promoted past the top level: sent to a random level.
    Wrapped,
}

/// legged_gym's terrain curriculum: a level and a terrain type per env.
///
/// Each env draws from its own ChaCha8 stream, so results do not depend on the
/// order in which envs are updated.
#[derive(Debug, Clone)]
pub struct Curriculum {
    levels: Vec<usize>,
    types: Vec<usize>,
    num_levels: usize,
    promote_distance_m: f64,
    rngs: Vec<ChaCha8Rng>,
}

impl Curriculum {
    /// Initial levels uniform in [0, max_init_level]; types spread evenly by env
    /// index (env e gets type floor(e * num_types / num_envs)).
    pub fn new(cfg: &TerrainConfig, num_envs: usize, seed: u64) -> Curriculum {
        let mut rngs: Vec<ChaCha8Rng> = (0..num_envs)
            .map(|e| {
                // Salted so a terrain and a curriculum built from one seed draw apart.
                let mut r = ChaCha8Rng::seed_from_u64(seed ^ CURRICULUM_SALT);
                r.set_stream(e as u64);
                r
            })
            .collect();
        let max_init = cfg.max_init_level.min(cfg.num_levels.saturating_sub(1));
        let levels = rngs.iter_mut().map(|r| r.gen_range(0..=max_init)).collect();
        let types = (0..num_envs)
            .map(|e| e * cfg.num_types / num_envs.max(1))
            .collect();
        Curriculum {
            levels,
            types,
            num_levels: cfg.num_levels,
            promote_distance_m: cfg.tile_length_m / 2.0,
            rngs,
        }
    }

    /// At the end of an episode of env `env`: promote when it walked more than half
    /// a tile, otherwise demote when it walked less than half of
    /// `commanded_distance_m` (= |v_cmd| x episode length). Promotion past the top
    /// level sends it to a random level in [0, num_levels - 1]; never below 0.
    pub fn update(
        &mut self,
        env: usize,
        distance_walked_m: f64,
        commanded_distance_m: f64,
    ) -> LevelChange {
        let level = self.levels[env];
        if distance_walked_m > self.promote_distance_m {
            if level + 1 >= self.num_levels {
                self.levels[env] = self.rngs[env].gen_range(0..self.num_levels);
                LevelChange::Wrapped
            } else {
                self.levels[env] = level + 1;
                LevelChange::Promoted
            }
        } else if distance_walked_m < 0.5 * commanded_distance_m && level > 0 {
            self.levels[env] = level - 1;
            LevelChange::Demoted
        } else {
            LevelChange::Unchanged
        }
    }

    pub fn num_envs(&self) -> usize {
        self.levels.len()
    }
    /// Puts every env back on a stored level; refuses a list of the wrong
    /// length or with a level beyond the terrain's.
    pub fn restore_levels(&mut self, levels: &[usize]) -> std::result::Result<(), String> {
        if levels.len() != self.levels.len() {
            return Err(format!(
                "{} stored terrain levels for {} envs",
                levels.len(),
                self.levels.len()
            ));
        }
        if let Some(l) = levels.iter().find(|&&l| l >= self.num_levels) {
            return Err(format!(
                "stored terrain level {l} but the terrain has {} levels",
                self.num_levels
            ));
        }
        self.levels.copy_from_slice(levels);
        Ok(())
    }
    /// Levels, types and every env's RNG, for an exact resume.
    pub fn snapshot(&self, w: &mut super::snapshot::StateWriter) {
        w.usize(self.levels.len());
        for ((l, t), r) in self.levels.iter().zip(&self.types).zip(&self.rngs) {
            w.usize(*l);
            w.usize(*t);
            w.rng(r);
        }
    }

    /// Restores [`Curriculum::snapshot`] (same env count, levels in range).
    pub fn restore(&mut self, r: &mut super::snapshot::StateReader) -> anyhow::Result<()> {
        let n = r.usize()?;
        anyhow::ensure!(
            n == self.levels.len(),
            "a curriculum of {n} envs for {} envs",
            self.levels.len()
        );
        for e in 0..n {
            let (level, terrain_type) = (r.usize()?, r.usize()?);
            anyhow::ensure!(
                level < self.num_levels,
                "stored terrain level {level} but the terrain has {} levels",
                self.num_levels
            );
            self.levels[e] = level;
            self.types[e] = terrain_type;
            self.rngs[e] = r.rng()?;
        }
        Ok(())
    }
    pub fn level(&self, env: usize) -> usize {
        self.levels[env]
    }
    pub fn terrain_type(&self, env: usize) -> usize {
        self.types[env]
    }
    pub fn levels(&self) -> &[usize] {
        &self.levels
    }
    pub fn types(&self) -> &[usize] {
        &self.types
    }
    /// Sets an env's level (evaluation, tests); clamped to the top level.
    pub fn set_level(&mut self, env: usize, level: usize) {
        self.levels[env] = level.min(self.num_levels - 1);
    }
    /// Mean level over envs (for logging); 0 with no envs.
    pub fn mean_level(&self) -> f64 {
        if self.levels.is_empty() {
            return 0.0;
        }
        self.levels.iter().sum::<usize>() as f64 / self.levels.len() as f64
    }
}
