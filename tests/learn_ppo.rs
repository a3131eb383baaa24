//! PPO learns a small continuous-control task with both critics.
//!
//! Task: a 2D point mass with damped velocity must reach and hold the origin.
//! `v' = 0.85 v + 0.25 clip(a, -1, 1)`, `p' = p + 0.1 v'`, reward `-|p'|` per
//! step, start at distance U(0.5, 1.5) at rest, observations `[p, v]` with
//! N(0, 0.02^2) noise. Episodes time out after 50 steps and terminate (reward
//! -20) beyond distance 2.5. A trained policy collects about -6.5; random and
//! initial policies about -50. Threshold: -9 within 100 iterations (64 envs x 24
//! steps each); measured: IQN passes at iteration 15, scalar at 15-20.

use rall::learn::{CriticKind, Learner, LearnerConfig, Rollout};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

const OBS: usize = 4;
const ACT: usize = 2;
const MAX_T: usize = 50;
const THRESHOLD: f32 = -9.0;

#[derive(Clone)]
struct PointMass {
    p: [f32; 2],
    v: [f32; 2],
    t: usize,
}

impl PointMass {
    fn new(rng: &mut impl Rng) -> Self {
        let angle = rng.gen_range(0.0..std::f32::consts::TAU);
        let r = rng.gen_range(0.5..1.5);
        PointMass {
            p: [r * angle.cos(), r * angle.sin()],
            v: [0.0; 2],
            t: 0,
        }
    }

    fn obs(&self, rng: &mut impl Rng, out: &mut Vec<f32>) {
        for x in [self.p[0], self.p[1], self.v[0], self.v[1]] {
            out.push(x + 0.02 * rng.sample::<f32, _>(StandardNormal));
        }
    }

    /// Returns (reward, terminated, timed_out).
    fn step(&mut self, a: &[f32]) -> (f32, bool, bool) {
        for ((v, p), a) in self.v.iter_mut().zip(&mut self.p).zip(a) {
            *v = 0.85 * *v + 0.25 * a.clamp(-1.0, 1.0);
            *p += 0.1 * *v;
        }
        self.t += 1;
        let d = (self.p[0] * self.p[0] + self.p[1] * self.p[1]).sqrt();
        if d > 2.5 {
            return (-20.0, true, false);
        }
        (-d, false, self.t >= MAX_T)
    }
}

/// Mean return of the deterministic policy over 32 fixed episodes.
fn evaluate(learner: &Learner) -> f32 {
    evaluate_with(|obs| learner.act_mean(obs))
}

fn evaluate_with(mut policy: impl FnMut(&[f32]) -> Vec<f32>) -> f32 {
    let mut rng = ChaCha8Rng::seed_from_u64(1234);
    let mut envs: Vec<PointMass> = (0..32).map(|_| PointMass::new(&mut rng)).collect();
    let mut ret = vec![0.0f32; envs.len()];
    let mut alive = vec![true; envs.len()];
    for _ in 0..MAX_T {
        let mut obs = Vec::new();
        envs.iter().for_each(|e| e.obs(&mut rng, &mut obs));
        let act = policy(&obs);
        for (i, env) in envs.iter_mut().enumerate() {
            if alive[i] {
                let (r, term, _) = env.step(&act[i * ACT..(i + 1) * ACT]);
                ret[i] += r;
                alive[i] = !term;
            }
        }
    }
    ret.iter().sum::<f32>() / ret.len() as f32
}

/// Trains until the evaluation passes THRESHOLD; returns (iterations, return).
fn train(critic: CriticKind, max_iters: usize) -> (usize, f32) {
    let cfg = LearnerConfig {
        critic,
        actor_hidden: vec![64, 64],
        critic_hidden: vec![64, 64],
        ..LearnerConfig::default()
    };
    let (num_envs, steps) = (64, 24);
    let mut learner = Learner::new(OBS, ACT, &cfg, 42).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut envs: Vec<PointMass> = (0..num_envs).map(|_| PointMass::new(&mut rng)).collect();
    let mut rollout = Rollout::new(steps, num_envs, OBS, ACT);
    let mut obs = Vec::new();
    envs.iter().for_each(|e| e.obs(&mut rng, &mut obs));
    let mut last = f32::NEG_INFINITY;
    for it in 1..=max_iters {
        rollout.clear();
        for _ in 0..steps {
            let out = learner.act(&obs, &mut rng);
            let (mut rew, mut done, mut tout) = (vec![], vec![], vec![]);
            let mut final_obs = vec![0.0; num_envs * OBS];
            let mut next = Vec::with_capacity(num_envs * OBS);
            for (i, env) in envs.iter_mut().enumerate() {
                let (r, term, to) = env.step(&out.actions[i * ACT..(i + 1) * ACT]);
                rew.push(r);
                done.push(term || to);
                tout.push(to && !term);
                if term || to {
                    let mut f = Vec::new();
                    env.obs(&mut rng, &mut f);
                    final_obs[i * OBS..(i + 1) * OBS].copy_from_slice(&f);
                    *env = PointMass::new(&mut rng);
                }
                env.obs(&mut rng, &mut next);
            }
            rollout
                .push(&obs, &out, &rew, &done, &tout, &final_obs)
                .unwrap();
            obs = next;
        }
        rollout.set_last_obs(&obs).unwrap();
        let stats = learner.update(&rollout).unwrap();
        assert!(stats.policy_loss.is_finite() && stats.value_loss.is_finite());
        if it % 5 == 0 {
            last = evaluate(&learner);
            if last > THRESHOLD {
                return (it, last);
            }
        }
    }
    (max_iters, last)
}

#[test]
fn random_policy_fails_the_threshold() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let random = evaluate_with(|obs| {
        (0..obs.len() / OBS * ACT)
            .map(|_| rng.gen_range(-1.0..1.0))
            .collect()
    });
    let learner = Learner::new(OBS, ACT, &LearnerConfig::default(), 42).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let initial = evaluate_with(|obs| learner.act(obs, &mut rng).actions);
    assert!(random < THRESHOLD - 15.0, "random policy return {random}");
    assert!(
        initial < THRESHOLD - 15.0,
        "initial policy return {initial}"
    );
}

#[test]
fn ppo_learns_with_iqn_cvar_critic() {
    let (iters, ret) = train(CriticKind::Iqn, 100);
    eprintln!("IQN (CVaR_0.5): return {ret} after {iters} iterations");
    assert!(
        ret > THRESHOLD,
        "IQN critic: return {ret} after {iters} iterations"
    );
}

#[test]
fn ppo_learns_with_scalar_critic() {
    let (iters, ret) = train(CriticKind::Scalar, 100);
    eprintln!("scalar: return {ret} after {iters} iterations");
    assert!(
        ret > THRESHOLD,
        "scalar critic: return {ret} after {iters} iterations"
    );
}

/// A small learner (64-32 networks, `critic`, `ppo`) and one rollout of 32 envs x 8
/// steps it collected from uniform random observations; each reward comes from
/// `reward` (given the stream the observations and actions are drawn from).
fn small_learner_and_rollout(
    critic: CriticKind,
    ppo: rall::learn::PpoConfig,
    seed: u64,
    mut reward: impl FnMut(&mut ChaCha8Rng) -> f32,
) -> (Learner, Rollout) {
    let cfg = LearnerConfig {
        critic,
        ppo,
        actor_hidden: vec![64, 32],
        critic_hidden: vec![64, 32],
        ..LearnerConfig::default()
    };
    let (envs, steps, obs_dim, act_dim) = (32, 8, 48, 12);
    let learner = Learner::new(obs_dim, act_dim, &cfg, 3).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut r = Rollout::new(steps, envs, obs_dim, act_dim);
    for _ in 0..steps {
        let obs: Vec<f32> = (0..envs * obs_dim)
            .map(|_| rng.gen_range(-1.0..1.0))
            .collect();
        let out = learner.act(&obs, &mut rng);
        let rew: Vec<f32> = (0..envs).map(|_| reward(&mut rng)).collect();
        r.push(
            &obs,
            &out,
            &rew,
            &vec![false; envs],
            &vec![false; envs],
            &[],
        )
        .unwrap();
    }
    r.set_last_obs(&vec![0.0; envs * obs_dim]).unwrap();
    (learner, r)
}

/// The adaptive learning rate reads KL(old || new): before any step (lr 0) the
/// policy is the one that collected, so KL and the clipped fraction are ~0.
#[test]
fn kl_is_zero_when_the_policy_has_not_moved() {
    use rall::learn::{LrSchedule, PpoConfig};
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let ppo = PpoConfig {
            learning_rate: 0.0,
            schedule: LrSchedule::Fixed,
            ..PpoConfig::default()
        };
        let (mut learner, r) = small_learner_and_rollout(critic, ppo, 4, |_| 0.5);
        let stats = learner.update(&r).unwrap();
        assert!(
            stats.approx_kl.abs() < 1e-6,
            "{critic:?}: kl {}",
            stats.approx_kl
        );
        assert_eq!(stats.clip_fraction, 0.0, "{critic:?}");
    }
}

/// The rates the Adam steps used are reported beside the end value: with the
/// adaptive rule they lie in [min_lr, max_lr], the end value among them; with a
/// fixed rate all three are that rate.
#[test]
fn the_update_reports_the_rates_its_steps_used() {
    use rall::learn::{LrSchedule, PpoConfig};
    for schedule in [LrSchedule::Adaptive, LrSchedule::Fixed] {
        let ppo = PpoConfig {
            learning_rate: 1e-3,
            schedule,
            ..PpoConfig::default()
        };
        let (min_lr, max_lr) = (ppo.min_lr, ppo.max_lr);
        let (mut learner, r) =
            small_learner_and_rollout(CriticKind::Scalar, ppo, 5, |rng| rng.gen_range(-1.0..1.0));
        for _ in 0..3 {
            let s = learner.update(&r).unwrap();
            match schedule {
                LrSchedule::Fixed => {
                    assert_eq!(s.learning_rate, 1e-3);
                    assert!((s.learning_rate_mean - 1e-3).abs() < 1e-9, "{s:?}");
                    assert_eq!(s.learning_rate_max, 1e-3);
                }
                LrSchedule::Adaptive => {
                    assert!(s.learning_rate <= s.learning_rate_max, "{s:?}");
                    assert!(s.learning_rate >= min_lr, "{s:?}");
                    assert!(
                        s.learning_rate_mean >= min_lr * 0.999
                            && s.learning_rate_mean <= s.learning_rate_max * 1.001,
                        "{s:?}"
                    );
                    assert!(s.learning_rate_max <= max_lr, "{s:?}");
                }
            }
        }
    }
}

/// `matmul = "bf16"` changes the update's products only: acting is the same f32
/// before the update, and one bf16 update moves the policy nearly as the f32 one.
#[test]
fn a_bf16_update_tracks_the_f32_one() {
    use rall::learn::mat::Precision;
    use rall::learn::{LrSchedule, PpoConfig};
    let obs: Vec<f32> = (0..4 * 48)
        .map(|i| ((i * 37) % 17) as f32 / 8.5 - 1.0)
        .collect();
    let dist = |a: &[f32], b: &[f32]| -> f32 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).powi(2))
            .sum::<f32>()
            .sqrt()
    };
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let run = |matmul: Precision| {
            let ppo = PpoConfig {
                matmul,
                schedule: LrSchedule::Fixed,
                learning_rate: 1e-3,
                ..PpoConfig::default()
            };
            let (mut learner, r) =
                small_learner_and_rollout(critic, ppo, 6, |rng| rng.gen_range(-1.0..1.0));
            let before = learner.act_mean(&obs);
            let stats = learner.update(&r).unwrap();
            (before, stats, learner.act_mean(&obs))
        };
        let (before32, s32, after32) = run(Precision::F32);
        let (before16, s16, after16) = run(Precision::Bf16);
        assert_eq!(before32, before16, "{critic:?}: acting is f32 either way");
        let moved = dist(&after32, &before32);
        let apart = dist(&after16, &after32);
        assert!(
            moved > 0.0,
            "{critic:?}: the update did not move the policy"
        );
        assert!(
            apart < 0.1 * moved,
            "{critic:?}: bf16 {apart} from f32, moved {moved}"
        );
        assert!(
            (s16.value_loss - s32.value_loss).abs() <= 0.02 * s32.value_loss.abs() + 1e-6,
            "{critic:?}: value loss {} vs {}",
            s16.value_loss,
            s32.value_loss
        );
        if rall::learn::amx::available() {
            assert!(apart > 0.0, "{critic:?}: bf16 ran the f32 kernels");
        }
    }
}

/// `matmul = "bf16-avx512"`: three updates with the products on AVX512-BF16 stay
/// close to three f32 updates (acting is f32 either way). On a CPU without the
/// instructions the setting falls back to f32, bit for bit, and the test says so.
#[test]
fn a_few_bf16_avx512_updates_track_f32() {
    use rall::learn::mat::{precision_available, precision_backend, Precision};
    use rall::learn::{LrSchedule, PpoConfig};
    let obs: Vec<f32> = (0..4 * 48)
        .map(|i| ((i * 37) % 17) as f32 / 8.5 - 1.0)
        .collect();
    let dist = |a: &[f32], b: &[f32]| -> f32 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).powi(2))
            .sum::<f32>()
            .sqrt()
    };
    let native = precision_available(Precision::Bf16Avx512);
    if !native {
        eprintln!(
            "no AVX512-BF16 on this CPU: bf16-avx512 runs {}; checking the fallback only",
            precision_backend(Precision::Bf16Avx512)
        );
    }
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let run = |matmul: Precision| {
            let ppo = PpoConfig {
                matmul,
                schedule: LrSchedule::Fixed,
                learning_rate: 1e-3,
                ..PpoConfig::default()
            };
            let (mut learner, r) =
                small_learner_and_rollout(critic, ppo, 6, |rng| rng.gen_range(-1.0..1.0));
            let before = learner.act_mean(&obs);
            let stats: Vec<_> = (0..3).map(|_| learner.update(&r).unwrap()).collect();
            (before, stats, learner.act_mean(&obs))
        };
        let (before32, s32, after32) = run(Precision::F32);
        let (before16, s16, after16) = run(Precision::Bf16Avx512);
        assert_eq!(before32, before16, "{critic:?}: acting is f32 either way");
        let (moved, apart) = (dist(&after32, &before32), dist(&after16, &after32));
        if !native {
            assert_eq!(apart, 0.0, "{critic:?}: the fallback is not f32");
            continue;
        }
        assert!(
            moved > 0.0,
            "{critic:?}: the updates did not move the policy"
        );
        assert!(apart > 0.0, "{critic:?}: bf16-avx512 ran the f32 kernels");
        assert!(
            apart < 0.1 * moved,
            "{critic:?}: bf16 {apart} from f32, moved {moved}"
        );
        for (u, (a, b)) in s16.iter().zip(&s32).enumerate() {
            assert!(
                (a.value_loss - b.value_loss).abs() <= 0.02 * b.value_loss.abs() + 1e-6,
                "{critic:?} update {u}: value loss {} vs {}",
                a.value_loss,
                b.value_loss
            );
            assert!(
                (a.policy_loss - b.policy_loss).abs() <= 0.05 * b.policy_loss.abs() + 1e-3,
                "{critic:?} update {u}: policy loss {} vs {}",
                a.policy_loss,
                b.policy_loss
            );
        }
    }
}
