//! The learner: networks, risk measures, rollout storage and the PPO update.
//! Compiles without MuJoCo (`cargo check --no-default-features --lib`).
