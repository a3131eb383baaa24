//! The data-parallel update. Ranks are simulated by threads that sum
//! through a barrier (`learn::collective::threads`), so these run without MPI;
//! `tests/mpi.rs` runs the real thing under `mpirun`.

use rall::learn::collective::threads::ThreadRanks;
use rall::learn::{ActOutput, CriticKind, Learner, LearnerConfig, Rollout, UpdateStats};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const OBS: usize = 10;
const ACT: usize = 3;
const STEPS: usize = 8;
const ENVS: usize = 16;

fn config(critic: CriticKind, epochs: usize, mini_batches: usize) -> LearnerConfig {
    let mut c = LearnerConfig {
        critic,
        actor_hidden: vec![32, 32],
        critic_hidden: vec![32, 32],
        num_taus: 8,
        num_target_taus: 8,
        num_value_taus: 8,
        ..Default::default()
    };
    c.ppo.num_learning_epochs = epochs;
    c.ppo.num_mini_batches = mini_batches;
    c
}

/// One rank's data for `STEPS` steps of `ENVS` envs: observations, the
/// policy's outputs on them, rewards and terminations.
struct StepData {
    obs: Vec<f32>,
    act: ActOutput,
    rewards: Vec<f32>,
    dones: Vec<bool>,
    time_outs: Vec<bool>,
    final_obs: Vec<f32>,
}

fn rank_data(learner: &Learner, seed: u64) -> (Vec<StepData>, Vec<f32>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut normal = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect() };
    let mut steps = Vec::new();
    for _ in 0..STEPS {
        let obs = normal(ENVS * OBS);
        let mut act_rng = ChaCha8Rng::seed_from_u64(seed ^ 0x55);
        let act = learner.act(&obs, &mut act_rng);
        let rewards = normal(ENVS);
        let final_obs = normal(ENVS * OBS);
        let dones: Vec<bool> = rewards.iter().map(|r| *r > 0.8).collect();
        let time_outs: Vec<bool> = rewards.iter().map(|r| *r > 0.9).collect();
        steps.push(StepData {
            obs,
            act,
            rewards,
            dones,
            time_outs,
            final_obs,
        });
    }
    (steps, normal(ENVS * OBS))
}

/// A rollout over the envs of several ranks side by side (rank 0's envs first).
fn rollout(parts: &[&(Vec<StepData>, Vec<f32>)]) -> Rollout {
    let mut r = Rollout::new(STEPS, ENVS * parts.len(), OBS, ACT);
    for t in 0..STEPS {
        let cat = |f: &dyn Fn(&StepData) -> Vec<f32>| -> Vec<f32> {
            parts.iter().flat_map(|p| f(&p.0[t])).collect()
        };
        let catb = |f: &dyn Fn(&StepData) -> Vec<bool>| -> Vec<bool> {
            parts.iter().flat_map(|p| f(&p.0[t])).collect()
        };
        let act = ActOutput {
            actions: cat(&|s| s.act.actions.clone()),
            log_probs: cat(&|s| s.act.log_probs.clone()),
            action_mean: cat(&|s| s.act.action_mean.clone()),
            action_std: cat(&|s| s.act.action_std.clone()),
        };
        r.push(
            &cat(&|s| s.obs.clone()),
            &act,
            &cat(&|s| s.rewards.clone()),
            &catb(&|s| s.dones.clone()),
            &catb(&|s| s.time_outs.clone()),
            &cat(&|s| s.final_obs.clone()),
        )
        .unwrap();
    }
    let last: Vec<f32> = parts.iter().flat_map(|p| p.1.clone()).collect();
    r.set_last_obs(&last).unwrap();
    r
}

fn weights(l: &Learner) -> Vec<f32> {
    l.state().into_iter().flat_map(|t| t.data).collect()
}

/// Each of `n` ranks (threads) updates `updates` times on its own rollout;
/// returns every rank's final state and its last update's statistics.
fn train_ranks(
    cfg: &LearnerConfig,
    rollouts: Vec<Rollout>,
    updates: usize,
) -> Vec<(Vec<f32>, UpdateStats)> {
    let comms = ThreadRanks::group(rollouts.len());
    std::thread::scope(|s| {
        let handles: Vec<_> = comms
            .into_iter()
            .zip(rollouts)
            .map(|(comm, r)| {
                s.spawn(move || {
                    let mut l = Learner::new(OBS, ACT, cfg, 3).unwrap();
                    let mut last = UpdateStats::default();
                    for _ in 0..updates {
                        last = l.update_with(&r, &comm).unwrap();
                    }
                    (weights(&l), last)
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    })
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn rel_diff(a: f32, b: f32) -> f32 {
    (a - b).abs() / a.abs().max(b.abs()).max(1e-12)
}

#[test]
fn two_ranks_average_to_the_gradient_of_one_process_over_the_union() {
    // one mini-batch per update, so each rank's mini-batch is half of the union's
    let cfg = config(CriticKind::Scalar, 1, 1);
    let init = Learner::new(OBS, ACT, &cfg, 3).unwrap();
    let (a, b) = (rank_data(&init, 1), rank_data(&init, 2));
    let updates = 3;
    let ranks = train_ranks(&cfg, vec![rollout(&[&a]), rollout(&[&b])], updates);

    let mut one = Learner::new(OBS, ACT, &cfg, 3).unwrap();
    let union = rollout(&[&a, &b]);
    let mut stats = UpdateStats::default();
    for _ in 0..updates {
        stats = one.update(&union).unwrap();
    }
    // the ranks agree bit for bit
    assert_eq!(ranks[0].0, ranks[1].0);
    let rs = &ranks[0].1;
    // the averaged gradient has the union's norm (per network), and the losses
    // and KL are the union's means
    for (x, y, what) in [
        (rs.grad_norm, stats.grad_norm, "gradient norm"),
        (
            rs.actor_grad_norm,
            stats.actor_grad_norm,
            "actor gradient norm",
        ),
        (
            rs.critic_grad_norm,
            stats.critic_grad_norm,
            "critic gradient norm",
        ),
        (rs.value_loss, stats.value_loss, "value loss"),
        (rs.approx_kl, stats.approx_kl, "KL"),
    ] {
        assert!(rel_diff(x, y) < 1e-4, "{what}: ranks {x} vs union {y}");
    }
    assert!((rs.policy_loss - stats.policy_loss).abs() < 1e-5);
    assert_eq!(rs.learning_rate, stats.learning_rate);
    // three Adam steps (the later ones depend on the gradients' magnitudes)
    let d = max_abs_diff(&ranks[0].0, &weights(&one));
    assert!(d < 1e-5, "weights differ by {d}");
    // and the ranks' data mattered: one rank alone would have moved elsewhere
    let mut alone = Learner::new(OBS, ACT, &cfg, 3).unwrap();
    for _ in 0..updates {
        alone.update(&rollout(&[&a])).unwrap();
    }
    assert!(max_abs_diff(&weights(&alone), &weights(&one)) > 1e-4);
}

#[test]
fn iqn_ranks_with_different_data_stay_identical_over_several_mini_batches() {
    let cfg = config(CriticKind::Iqn, 2, 2);
    let init = Learner::new(OBS, ACT, &cfg, 3).unwrap();
    let data: Vec<_> = (0..3).map(|s| rank_data(&init, 10 + s)).collect();
    let rollouts = data.iter().map(|d| rollout(&[d])).collect();
    let ranks = train_ranks(&cfg, rollouts, 2);
    assert_eq!(ranks[0].0, ranks[1].0);
    assert_eq!(ranks[0].0, ranks[2].0);
    assert!(
        max_abs_diff(&ranks[0].0, &weights(&init)) > 1e-5,
        "it learned"
    );
}
