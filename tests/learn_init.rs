//! `learner.actor_output_init_scale` scales the actor's output
//! layer at initialisation and nothing else.

use rall::learn::{Learner, LearnerConfig};

#[test]
fn a_small_output_init_scales_only_the_actor_output_layer() {
    let (obs_dim, act_dim) = (48, 12);
    let plain = Learner::new(obs_dim, act_dim, &LearnerConfig::default(), 7).unwrap();
    let cfg = LearnerConfig {
        actor_output_init_scale: 0.01,
        ..LearnerConfig::default()
    };
    let small = Learner::new(obs_dim, act_dim, &cfg, 7).unwrap();
    let last = format!("actor.l{}.", cfg.actor_hidden.len());
    let (a, b) = (plain.state(), small.state());
    assert_eq!(a.len(), b.len());
    let mut scaled = 0;
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.name, y.name);
        if x.name.starts_with(&last) {
            scaled += 1;
            for (p, q) in x.data.iter().zip(&y.data) {
                assert_eq!(p * 0.01, *q, "{}", x.name);
            }
        } else {
            assert_eq!(x.data, y.data, "{}", x.name);
        }
    }
    assert_eq!(scaled, 2, "the output layer's weight and bias");
    // the first actions sit near the default pose
    let obs: Vec<f32> = (0..16 * obs_dim)
        .map(|i| ((i % 7) as f32 - 3.0) * 0.3)
        .collect();
    let max = |v: Vec<f32>| v.iter().fold(0.0f32, |m, a| m.max(a.abs()));
    let (big, tiny) = (max(plain.act_mean(&obs)), max(small.act_mean(&obs)));
    assert!(tiny < 0.02 * big.max(0.1), "{tiny} against {big}");

    let bad = LearnerConfig {
        actor_output_init_scale: 0.0,
        ..LearnerConfig::default()
    };
    let err = bad.validate().unwrap_err().to_string();
    assert!(err.contains("actor_output_init_scale"), "{err}");
}
