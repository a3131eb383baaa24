//! A critic defined outside the crate: a scalar head trained by the Huber loss,
//! registered with one `register` call. Its loss and gradient, a short run
//! through the runner, its checkpoint and exact resume, and the registry's
//! refusals.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, OnceLock};

use anyhow::Result;
use rall::config::TrainConfig;
use rall::learn::critic::{CriticCache, LossInput, TargetInput, Targets};
use rall::learn::nets::{InputSel, MlpCache, ParamSet, ScalarCritic};
use rall::learn::ppo::CriticLossConfig;
use rall::learn::storage::{gae, next_values};
use rall::learn::{
    read_checkpoint, register, Critic, CriticKind, CriticSpec, LearnerConfig, PpoConfig,
};
use rall::runner::{load_policy, train, LATEST};
use rand::{Rng, RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod common;
use common::{metrics_without_timing, tiny_config};

/// `V(s)` regressed on the GAE returns by the Huber loss with threshold `delta`
/// (the config's `kappa`).
#[derive(Clone, Debug)]
struct HuberCritic {
    net: ScalarCritic,
    delta: f32,
}

fn build_huber(
    input: InputSel,
    cfg: &LearnerConfig,
    mut rng: &mut dyn RngCore,
) -> Result<Box<dyn Critic>> {
    Ok(Box::new(HuberCritic {
        net: ScalarCritic::with_input(input, &cfg.critic_hidden, &mut rng),
        delta: cfg.kappa,
    }))
}

/// Huber loss of the residual `r`: `r^2 / 2` within `delta`, linear beyond.
fn huber(r: f64, delta: f64) -> f64 {
    if r.abs() <= delta {
        0.5 * r * r
    } else {
        delta * (r.abs() - 0.5 * delta)
    }
}

impl Critic for HuberCritic {
    fn params(&self) -> &ParamSet {
        &self.net.params
    }
    fn params_mut(&mut self) -> &mut ParamSet {
        &mut self.net.params
    }
    fn distorted_value(&self, obs: &[f32], n: usize, _value_taus: &[f32]) -> Vec<f32> {
        self.net.values(obs, n)
    }
    fn targets(
        &self,
        input: &TargetInput<'_>,
        _cache: &mut CriticCache,
        _rng: &mut dyn RngCore,
    ) -> Targets {
        let r = input.rollout;
        let v = |o: &[f32]| self.net.values(o, o.len() / r.obs_dim);
        let values = v(&r.obs);
        let next = next_values(r, 1, &values, &v(&r.last_obs), &v(input.finals));
        let adv = gae(r, &values, &next, input.cfg.gamma, input.cfg.lam);
        let value_targets = adv.iter().zip(&values).map(|(a, v)| a + v).collect();
        Targets { adv, value_targets }
    }
    fn forward_mini_batch(&self, obs: &[f32], n: usize, _: &[f32], cache: &mut CriticCache) {
        self.net.forward(obs, n, cache.get::<MlpCache>());
    }
    fn value_loss(
        &self,
        input: &LossInput<'_>,
        cache: &mut CriticCache,
        d_out: &mut Vec<f32>,
    ) -> f64 {
        let b = input.batch as f32;
        let v = cache.get::<MlpCache>().output();
        d_out.clear();
        let mut loss = 0.0;
        for (v, t) in v.iter().zip(input.targets) {
            let r = v - t;
            loss += huber(r as f64, self.delta as f64);
            d_out.push(input.cfg.value_loss_coef * r.clamp(-self.delta, self.delta) / b);
        }
        loss / b as f64
    }
    fn backward_mini_batch(
        &self,
        grads: &mut [f32],
        obs: &[f32],
        n: usize,
        cache: &mut CriticCache,
        d_out: &mut Vec<f32>,
    ) {
        self.net
            .backward(grads, obs, n, cache.get::<MlpCache>(), d_out);
    }
}

const HUBER: CriticSpec = CriticSpec {
    name: "huber",
    has_quantiles: false,
    build: build_huber,
};

/// The Huber critic's kind, registered once per test process.
fn huber_kind() -> CriticKind {
    static KIND: OnceLock<CriticKind> = OnceLock::new();
    *KIND.get_or_init(|| register(HUBER).unwrap())
}

fn no_stop() -> Arc<AtomicBool> {
    Arc::new(AtomicBool::new(false))
}

/// The loss of `critic` on `obs` against `targets` (one mini-batch, one shard)
/// and the gradient of its parameters.
fn loss_and_gradient(critic: &dyn Critic, obs: &[f32], targets: &[f32]) -> (f64, Vec<f32>) {
    let n = targets.len();
    let (cfg, ccfg) = (PpoConfig::default(), loss_config());
    let input = LossInput {
        samples: &[],
        targets,
        rows: n,
        batch: n,
        cfg: &cfg,
        ccfg: &ccfg,
    };
    let mut cache = CriticCache::default();
    let mut d_out = Vec::new();
    critic.forward_mini_batch(obs, n, &[], &mut cache);
    let loss = critic.value_loss(&input, &mut cache, &mut d_out);
    let mut grads = vec![0.0; critic.params().data.len()];
    critic.backward_mini_batch(&mut grads, obs, n, &mut cache, &mut d_out);
    (loss, grads)
}

fn loss_config() -> CriticLossConfig {
    CriticLossConfig {
        num_taus: 8,
        num_target_taus: 8,
        kappa: 1.0,
        target_lambda: 0.95,
    }
}

#[test]
fn the_huber_critic_computes_its_loss_and_gradient() {
    const OBS: usize = 3;
    const N: usize = 12;
    let cfg = LearnerConfig {
        critic: huber_kind(),
        critic_hidden: vec![8, 6],
        kappa: 0.5,
        cvar_eta: None,
        ..LearnerConfig::default()
    };
    cfg.validate().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut critic = huber_kind()
        .build(InputSel::all(OBS), &cfg, &mut rng)
        .unwrap();
    let obs: Vec<f32> = (0..N * OBS).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let targets: Vec<f32> = (0..N).map(|_| rng.gen_range(-2.0..2.0)).collect();

    // the loss: the mean Huber loss of V(s) - target (residuals on both sides of delta)
    let values = critic.distorted_value(&obs, N, &[]);
    let residuals: Vec<f64> = values
        .iter()
        .zip(&targets)
        .map(|(v, t)| (v - t) as f64)
        .collect();
    assert!(residuals.iter().any(|r| r.abs() < 0.5) && residuals.iter().any(|r| r.abs() > 0.5));
    let expected = residuals.iter().map(|&r| huber(r, 0.5)).sum::<f64>() / N as f64;
    let (loss, grads) = loss_and_gradient(critic.as_ref(), &obs, &targets);
    assert!((loss - expected).abs() < 1e-6, "{loss} vs {expected}");
    // without a distribution, every quantile is V(s)
    let z = critic.value_quantiles(&obs, N, &[0.1, 0.9]);
    assert_eq!(z, values.iter().flat_map(|&v| [v, v]).collect::<Vec<_>>());

    // the gradient: central differences of the loss in every parameter
    let eps = 1e-3;
    let mut worst = 0.0f64;
    for (i, &g) in grads.iter().enumerate() {
        let at = |critic: &mut Box<dyn Critic>, x: f32| {
            critic.params_mut().data[i] = x;
            loss_and_gradient(critic.as_ref(), &obs, &targets).0
        };
        let p = critic.params().data[i];
        let (hi, lo) = (p + eps, p - eps);
        let fd = (at(&mut critic, hi) - at(&mut critic, lo)) / (hi - lo) as f64;
        critic.params_mut().data[i] = p;
        let err = (fd - g as f64).abs() / (1e-2 + (g as f64).abs());
        worst = worst.max(err);
        assert!(err < 2e-2, "parameter {i}: analytic {g} vs numeric {fd}");
    }
    assert!(
        grads.iter().any(|g| g.abs() > 1e-3),
        "the gradient is not all zero"
    );
    eprintln!("worst relative gradient error {worst:.2e}");
}

/// Every tensor of the run's latest checkpoint, as bits.
fn tensor_bits(run: &Path) -> Vec<(String, Vec<u32>)> {
    read_checkpoint(&run.join(LATEST))
        .unwrap()
        .tensors
        .into_iter()
        .map(|t| (t.name, t.data.iter().map(|v| v.to_bits()).collect()))
        .collect()
}

fn huber_config(iterations: usize) -> TrainConfig {
    let mut c = tiny_config(huber_kind());
    c.runner.iterations = iterations;
    c
}

#[test]
fn the_huber_critic_trains_checkpoints_and_resumes_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let whole = dir.path().join("whole");
    train(huber_config(3), &whole, false, no_stop(), &mut ()).unwrap();
    let text = std::fs::read_to_string(whole.join("metrics.csv")).unwrap();
    let head: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    let col = head.iter().position(|h| *h == "value_loss").unwrap();
    for row in text.lines().skip(1) {
        let v: f32 = row.split(',').nth(col).unwrap().parse().unwrap();
        assert!(v.is_finite() && v > 0.0, "value_loss {v}");
    }
    let stored = std::fs::read_to_string(whole.join("config.toml")).unwrap();
    assert!(stored.contains("critic = \"huber\""), "{stored}");

    // the checkpoint loads into a Huber learner holding exactly its tensors
    let p = load_policy(&whole.join(LATEST)).unwrap();
    assert_eq!(p.config.learner.critic, huber_kind());
    assert_eq!(p.config.learner.risk_label(), "huber");
    let file = tensor_bits(&whole);
    let state = p.learner.state();
    assert!(state.iter().any(|t| t.name == "critic.l0.weight"));
    for t in &state {
        let (_, bits) = file.iter().find(|(n, _)| *n == t.name).unwrap();
        let own: Vec<u32> = t.data.iter().map(|v| v.to_bits()).collect();
        assert_eq!(&own, bits, "tensor {}", t.name);
    }

    // stopped after 2 iterations and resumed to 3: the same run, bit for bit
    let resumed = dir.path().join("resumed");
    train(huber_config(2), &resumed, false, no_stop(), &mut ()).unwrap();
    let s = train(huber_config(3), &resumed, true, no_stop(), &mut ()).unwrap();
    assert_eq!(s.iterations_done, 3);
    assert_eq!(tensor_bits(&whole), tensor_bits(&resumed));
    assert_eq!(
        metrics_without_timing(&whole),
        metrics_without_timing(&resumed)
    );
}

#[test]
fn the_registry_refuses_unknown_and_taken_names() {
    huber_kind();
    let e = CriticKind::from_name("no-such-critic")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("\"no-such-critic\"") && e.contains("huber"),
        "{e}"
    );
    let e = TrainConfig::from_toml_str("[learner]\ncritic = \"no-such-critic\"\n").unwrap_err();
    assert!(format!("{e:#}").contains("no-such-critic"), "{e:#}");
    for taken in ["iqn", "scalar", "huber"] {
        let e = register(CriticSpec {
            name: taken,
            ..HUBER
        })
        .unwrap_err()
        .to_string();
        assert!(
            e.contains(&format!("{taken:?}")) && e.contains("taken"),
            "{e}"
        );
    }
    let e = register(CriticSpec {
        name: "Huber Loss",
        ..HUBER
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("\"Huber Loss\""), "{e}");
    // a critic without quantiles refuses a distortion, naming itself
    let cfg = LearnerConfig {
        critic: huber_kind(),
        cvar_eta: Some(0.5),
        ..LearnerConfig::default()
    };
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("\"huber\"") && e.contains("cvar_eta"), "{e}");
}
