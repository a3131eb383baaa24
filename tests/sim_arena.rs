//! MuJoCo's arena is sized to what the Aliengo needs. The scene's
//! `<size nconmax njmax>` bounds each env's mjData (its constraint matrices grow
//! with njmax squared); this checks the sizes hold what training on rough ground
//! uses, random actions included (stumbles, falls), with room to spare.

use std::sync::Arc;

use rall::env::terrain::TerrainKind;
use rall::env::{build_scene, EnvConfig, VecEnv, ACT_DIM};
use rand::{Rng, SeedableRng};

#[test]
fn the_sized_arena_holds_rough_ground_with_random_actions() {
    let mut cfg = EnvConfig {
        robot_mjcf: concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml").into(),
        ..Default::default()
    };
    cfg.terrain.kind = TerrainKind::Rough;
    cfg.episode.length_s = 4.0;
    let cfg = Arc::new(cfg);
    let scene = build_scene(&cfg, 3).unwrap();
    let n = 32;
    let mut v = VecEnv::new(cfg, &scene.model, scene.terrain.clone(), n, 2, 3).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let mut episodes = 0;
    for _ in 0..600 {
        let a: Vec<f32> = (0..n * ACT_DIM).map(|_| rng.gen_range(-1.0..1.0)).collect();
        v.step(&a);
        episodes += v.drain_episodes().count();
    }
    let most = v.max_arena_use();
    println!("arena use over {episodes} episodes: {most:?}");
    assert!(episodes > n, "episodes ended and reset: {episodes}");
    assert_eq!(v.instabilities(), 0, "no env ran out of arena: {most:?}");
    assert!(
        most.contacts < most.contacts_max && most.constraints < most.constraints_max,
        "{most:?}"
    );
    assert!(most.stack * 2 <= most.stack_max, "{most:?}");
    // Sized: not the old 600 rows (4.7 MB of dense matrices per env).
    assert!(most.constraints_max <= 300, "{most:?}");
}
