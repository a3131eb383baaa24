//! Learner state through safetensors checkpoints, refusal of mismatches, and
//! seed determinism.

use rall::learn::{
    load_checkpoint, save_checkpoint, CriticKind, Learner, LearnerConfig, NamedTensor, Rollout,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::HashMap;

const OBS: usize = 5;
const ACT: usize = 3;

fn cfg(critic: CriticKind) -> LearnerConfig {
    LearnerConfig {
        critic,
        actor_hidden: vec![16, 8],
        critic_hidden: vec![16, 8],
        ..LearnerConfig::default()
    }
}

fn obs(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n * OBS).map(|_| rng.gen_range(-1.0..1.0)).collect()
}

/// A full random rollout, so that the Adam moments and lr are non-trivial.
fn trained(critic: CriticKind, seed: u64) -> Learner {
    let mut learner = Learner::new(OBS, ACT, &cfg(critic), seed).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed + 1);
    let (steps, envs) = (8, 4);
    let mut r = Rollout::new(steps, envs, OBS, ACT);
    for t in 0..steps {
        let o = obs(envs, 100 + t as u64);
        let out = learner.act(&o, &mut rng);
        let rew: Vec<f32> = (0..envs).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let done = vec![t == 5; envs];
        let tout = vec![t == 5; envs];
        r.push(&o, &out, &rew, &done, &tout, &obs(envs, 200))
            .unwrap();
    }
    r.set_last_obs(&obs(envs, 300)).unwrap();
    learner.update(&r).unwrap();
    learner
}

fn outputs(l: &Learner) -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
    let o = obs(6, 9);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    (
        l.act_mean(&o),
        l.value_quantiles(&o, &[0.1, 0.5, 0.9]),
        l.distorted_value(&o),
        l.act(&o, &mut rng).actions,
    )
}

#[test]
fn save_load_roundtrip_gives_identical_outputs() {
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ckpt.safetensors");
        let a = trained(critic, 1);
        let meta = HashMap::from([
            (
                "config".to_string(),
                serde_json::to_string(a.config()).unwrap(),
            ),
            ("version".to_string(), "test".to_string()),
        ]);
        save_checkpoint(&path, &a.state(), &meta).unwrap();
        assert!(!dir.path().join("ckpt.safetensors.tmp").exists());
        let (tensors, meta2) = load_checkpoint(&path).unwrap();
        assert_eq!(meta2, meta);
        let cfg2: LearnerConfig = serde_json::from_str(&meta2["config"]).unwrap();
        let mut b = Learner::new(OBS, ACT, &cfg2, 99).unwrap();
        assert_ne!(outputs(&a), outputs(&b));
        b.load_state(&tensors).unwrap();
        assert_eq!(outputs(&a), outputs(&b));
        assert_eq!(a.state(), b.state());
        assert_eq!(a.learning_rate(), b.learning_rate());
        let names: Vec<&str> = tensors.iter().map(|t| t.name.as_str()).collect();
        for n in [
            "adam.step",
            "lr",
            "actor.log_std",
            "adam.m.actor.l0.weight",
            "adam.v.critic.l0.bias",
        ] {
            let n = if critic == CriticKind::Iqn {
                n.replace("critic.l0", "critic.trunk.l0")
            } else {
                n.to_string()
            };
            assert!(names.contains(&n.as_str()), "{n} missing from {names:?}");
        }
    }
}

#[test]
fn mismatched_shape_is_refused_naming_the_tensor() {
    let a = Learner::new(OBS, ACT, &cfg(CriticKind::Iqn), 1).unwrap();
    let wider = LearnerConfig {
        actor_hidden: vec![16, 9],
        ..cfg(CriticKind::Iqn)
    };
    let mut b = Learner::new(OBS, ACT, &wider, 1).unwrap();
    let before = b.state();
    let err = b.load_state(&a.state()).unwrap_err().to_string();
    assert!(
        err.contains("actor.l1.weight") && err.contains("[16, 8]") && err.contains("[16, 9]"),
        "{err}"
    );
    assert_eq!(b.state(), before, "a refused load must change nothing");

    // a missing tensor (scalar-critic checkpoint into an IQN learner)
    let s = Learner::new(OBS, ACT, &cfg(CriticKind::Scalar), 1).unwrap();
    let mut iqn = Learner::new(OBS, ACT, &cfg(CriticKind::Iqn), 1).unwrap();
    let err = iqn.load_state(&s.state()).unwrap_err().to_string();
    assert!(
        err.contains("missing tensor `critic.trunk.l0.weight`"),
        "{err}"
    );
    let mut partial: Vec<NamedTensor> = a.state();
    partial.retain(|t| t.name != "lr");
    assert!(iqn
        .load_state(&partial)
        .unwrap_err()
        .to_string()
        .contains("`lr`"));
}

#[test]
fn truncated_or_corrupt_file_is_an_error_naming_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ckpt.safetensors");
    let a = Learner::new(OBS, ACT, &cfg(CriticKind::Iqn), 1).unwrap();
    save_checkpoint(&path, &a.state(), &HashMap::new()).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    for cut in [bytes.len() - 1, bytes.len() / 2, 40, 7, 0] {
        std::fs::write(&path, &bytes[..cut]).unwrap();
        let err = format!("{:#}", load_checkpoint(&path).unwrap_err());
        assert!(err.contains("ckpt.safetensors"), "cut {cut}: {err}");
    }
    std::fs::write(&path, b"\xff\xff\xff\xff\xff\xff\xff\x7fnot a header").unwrap();
    assert!(load_checkpoint(&path).is_err());
    let missing = dir.path().join("nope.safetensors");
    assert!(format!("{:#}", load_checkpoint(&missing).unwrap_err()).contains("nope.safetensors"));
}

#[test]
fn same_seed_same_weights_and_actions() {
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let a = Learner::new(OBS, ACT, &cfg(critic), 5).unwrap();
        let b = Learner::new(OBS, ACT, &cfg(critic), 5).unwrap();
        assert_eq!(a.state(), b.state());
        assert_eq!(outputs(&a), outputs(&b));
        let c = Learner::new(OBS, ACT, &cfg(critic), 6).unwrap();
        assert_ne!(a.state(), c.state());
        // and the updates are reproducible too
        assert_eq!(trained(critic, 2).state(), trained(critic, 2).state());
    }
}
