//! Builds the MuJoCo scene of a task: the robot MJCF plus the ground.

use std::sync::Arc;

use super::config::EnvConfig;
use super::terrain::{Terrain, TerrainKind};
use crate::sim::{Model, Result, SimError};

/// The loaded scene and, on rough ground, the terrain it was made from. The
/// model is shared by every env built on it (the terrain is stored once).
pub struct Scene {
    pub model: Arc<Model>,
    pub terrain: Option<Arc<Terrain>>,
}

/// Reads `cfg.robot_mjcf`, adds the ground (plane or heightfield from
/// `cfg.terrain`, generated from `seed`) and loads it.
pub fn build_scene(cfg: &EnvConfig, seed: u64) -> Result<Scene> {
    let (path, robot_xml) = cfg
        .read_robot_mjcf()
        .map_err(|(path, reason)| SimError::ModelFile { path, reason })?;
    let terrain = Terrain::generate(&cfg.terrain, seed);
    let scene_xml = terrain
        .scene_xml(&robot_xml)
        .map_err(|e| SimError::Invalid(format!("{}: {e}", path.display())))?;
    let mut model = Model::from_xml_str(
        &scene_xml,
        &format!("{} + {:?} terrain", path.display(), cfg.terrain.kind),
    )?;
    terrain.upload(&mut model).map_err(SimError::Invalid)?;
    let terrain = (cfg.terrain.kind != TerrainKind::Flat).then(|| Arc::new(terrain));
    Ok(Scene {
        model: Arc::new(model),
        terrain,
    })
}
