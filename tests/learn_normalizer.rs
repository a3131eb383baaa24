//! The empirical observation normaliser (`learner.obs_normalization`).
//! Acting, the update and checkpoints all see the same statistics, which learn
//! from every rollout after its update.

use rall::learn::{
    CriticKind, EmpiricalNormalizer, EncoderConfig, Learner, LearnerConfig, LrSchedule, PpoConfig,
    Rollout, SingleProcess,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const ENVS: usize = 16;
const STEPS: usize = 8;
const OBS: usize = 6;
const ACT: usize = 2;

fn config(critic: CriticKind, obs_normalization: bool) -> LearnerConfig {
    LearnerConfig {
        critic,
        actor_hidden: vec![32, 16],
        critic_hidden: vec![32, 16],
        obs_normalization,
        ..LearnerConfig::default()
    }
}

/// Observations far from unit scale: column `j` is `10 j - 20 + (j + 1) U(-1, 1)`.
fn skewed_obs(rng: &mut ChaCha8Rng) -> Vec<f32> {
    (0..ENVS * OBS)
        .map(|i| {
            let j = (i % OBS) as f32;
            10.0 * j - 20.0 + (j + 1.0) * rng.gen_range(-1.0f32..1.0)
        })
        .collect()
}

/// One rollout `learner` collected on skewed observations, with a time-out (and
/// its final observation) every third step in env 0.
fn collect(learner: &Learner, seed: u64) -> Rollout {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut r = Rollout::new(STEPS, ENVS, OBS, ACT);
    for t in 0..STEPS {
        let obs = skewed_obs(&mut rng);
        let out = learner.act(&obs, &mut rng);
        let rew: Vec<f32> = (0..ENVS).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let mut ends = vec![false; ENVS];
        ends[0] = t % 3 == 2;
        let final_obs = if ends[0] {
            skewed_obs(&mut rng)
        } else {
            vec![]
        };
        r.push(&obs, &out, &rew, &ends, &ends, &final_obs).unwrap();
    }
    r.set_last_obs(&skewed_obs(&mut rng)).unwrap();
    r
}

/// With a zero learning rate the update's first look at the policy must find the
/// one that collected (KL 0): the update normalises the rollout exactly as
/// acting did. Reading raw rows would give a different policy and a large KL.
#[test]
fn the_update_sees_the_policy_that_collected() {
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let cfg = LearnerConfig {
            ppo: PpoConfig {
                learning_rate: 0.0,
                schedule: LrSchedule::Fixed,
                ..PpoConfig::default()
            },
            ..config(critic, true)
        };
        let mut learner = Learner::new(OBS, ACT, &cfg, 5).unwrap();
        // statistics that differ from the initial ones, before collecting
        let warmup = collect(&learner, 1);
        learner.update(&warmup).unwrap();
        let r = collect(&learner, 2);
        let stats = learner.update(&r).unwrap();
        assert!(
            stats.approx_kl.abs() < 1e-6,
            "{critic:?}: KL {}",
            stats.approx_kl
        );
        assert_eq!(stats.clip_fraction, 0.0, "{critic:?}");
    }
}

#[test]
fn statistics_learn_from_rollouts_and_the_networks_read_normalised_rows() {
    let mut learner = Learner::new(OBS, ACT, &config(CriticKind::Iqn, true), 5).unwrap();
    let r = collect(&learner, 3);
    learner.update(&r).unwrap();
    let norm = learner.obs_normalizer().expect("normaliser configured");
    assert_eq!(norm.count(), (ENVS * STEPS) as u64);
    // exactly the statistics of the rollout's observations (the normaliser's own
    // arithmetic is checked against direct sums in src/learn/normalizer.rs)
    let mut expected = EmpiricalNormalizer::new(OBS);
    expected.update(&r.obs, &SingleProcess);
    assert_eq!(norm, &expected);
    assert!(norm.mean()[OBS - 1] > 25.0, "column 5 sits near 30");
    // the same weights without a normaliser, fed the normalised rows, act alike
    let mut plain = Learner::new(OBS, ACT, &config(CriticKind::Iqn, false), 9).unwrap();
    plain.load_state(&learner.state()).unwrap();
    let raw = skewed_obs(&mut ChaCha8Rng::seed_from_u64(4));
    let mut normalised = raw.clone();
    norm.normalize_in_place(&mut normalised);
    assert_eq!(learner.act_mean(&raw), plain.act_mean(&normalised));
    assert_eq!(
        learner.distorted_value(&raw),
        plain.distorted_value(&normalised)
    );
    assert_ne!(learner.act_mean(&raw), plain.act_mean(&raw));
    // a second rollout moves the statistics on
    let before = norm.clone();
    let r2 = collect(&learner, 6);
    learner.update(&r2).unwrap();
    let after = learner.obs_normalizer().unwrap();
    assert_eq!(after.count(), 2 * (ENVS * STEPS) as u64);
    assert_ne!(after.mean(), before.mean());
}

#[test]
fn checkpoints_carry_the_statistics() {
    let cfg = config(CriticKind::Scalar, true);
    let mut learner = Learner::new(OBS, ACT, &cfg, 5).unwrap();
    learner.update(&collect(&learner, 7)).unwrap();
    let state = learner.state();
    assert!(state.iter().any(|t| t.name == "obs_norm.mean"));

    let mut resumed = Learner::new(OBS, ACT, &cfg, 11).unwrap();
    resumed.load_state(&state).unwrap();
    assert_eq!(resumed.obs_normalizer(), learner.obs_normalizer());
    let raw = skewed_obs(&mut ChaCha8Rng::seed_from_u64(8));
    assert_eq!(resumed.act_mean(&raw), learner.act_mean(&raw));
    // both merge the next rollout alike (their update RNGs differ: a resumed run
    // reseeds it, so the weights may not)
    let r = collect(&learner, 9);
    learner.update(&r).unwrap();
    resumed.update(&r).unwrap();
    assert_eq!(resumed.obs_normalizer(), learner.obs_normalizer());
    let own = resumed.act_mean(&raw);

    // a checkpoint trained without the normaliser is refused by name, unchanged
    let plain = Learner::new(OBS, ACT, &config(CriticKind::Scalar, false), 5).unwrap();
    let err = resumed.load_state(&plain.state()).unwrap_err();
    assert!(err.to_string().contains("obs_norm.mean"), "{err}");
    assert_eq!(resumed.act_mean(&raw), own);
    // and corrupt statistics are refused, changing nothing
    let mut bad = learner.state();
    let var = bad.iter_mut().find(|t| t.name == "obs_norm.var").unwrap();
    var.data[0] = f32::NAN;
    let err = resumed.load_state(&bad).unwrap_err();
    assert!(err.to_string().contains("obs_norm"), "{err}");
    assert_eq!(resumed.act_mean(&raw), own);
}

#[test]
fn rma_with_the_normaliser_is_refused_by_name() {
    let cfg = LearnerConfig {
        encoder: Some(EncoderConfig::default()),
        ..config(CriticKind::Scalar, true)
    };
    let err = cfg.validate().unwrap_err().to_string();
    assert!(
        err.contains("obs_normalization") && err.contains("encoder"),
        "{err}"
    );
}
