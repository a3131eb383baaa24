//! `rall`: risk-averse legged locomotion (RALL) on CPU.
//!
//! Layers, top to bottom (dependencies only point down):
//! - [`sim`]: the only module with `unsafe`; safe types over MuJoCo 2.2.
//! - [`robot`]: the Aliengo description (joint order, PD control, standing check).
//! - [`learn`]: CVaR-PPO with an IQN critic; knows nothing of MuJoCo.
//! - [`hash`]: FNV-1a, the crate's one stable hash (no dependencies).
//! - [`progress`]: the one look of the progress bars (training, evaluation).
//! - [`stats`]: means, interpolated quantiles, estimates with intervals and the bootstrap,
//!   one definition for `eval` and `experiment`; the seed-level tests that decide between
//!   methods.
//! - [`fsio`]: atomic whole-file writes ([`fsio::write_atomic`]) and rall's temp-file names.
//! - [`memory`]: the process's allocator (large buffers on transparent huge pages).
//! - `env`: one robot's task (observation groups, reward, risk, commands, terrain and its
//!   curriculum, randomisation) and `VecEnv`, N of them on a rayon pool.
//! - `runner`: the training loop, run directories, checkpoints on disk, metrics, MPI.
//! - `eval`: tracking, the robustness scenarios and benchmarks (TTF, platform, race, the
//!   meta controller), the severity ladder, risk calibration.
//! - `experiment`: `rall experiment` (runs, selection, K checkpoints, tables, curves, figures).
//! - `export`, `viz`, `config`, `cli`: ONNX and its sidecar; rerun recordings; the run
//!   config; the subcommands. (These need the default `sim` feature.)
//!
//! Module map, every file (each opens with a paragraph on what it holds); the
//! top-level `config`, `fsio`, `hash`, `memory` and `progress` are in the layers above,
//! and `main.rs` is the `rall` binary over `cli`:
//! - `sim`: `data`, `error`, `ffi` (bindgen), `model`, `shim` (guarded MuJoCo calls).
//! - `robot`: `layout` (parts by name), `params` (randomisable values), `pd` (torques),
//!   `standing` (the standing check).
//! - `learn`: `actor_critic`, `nets` (MLP and IQN with hand-written backward), `mat`,
//!   `amx` and `bf16_avx512` (kernels), `adam`, `ppo` (the update), `storage` (rollout, GAE, IQN targets),
//!   `risk` (distortions, quantile Huber), `normalizer`, `adaptation` (RMA phase 2),
//!   `layout` (observation groups), `checkpoint` (safetensors), `collective` (sums across
//!   ranks), `critic` (the critic trait; `iqn`, `scalar`), `learner` (the facade the runner
//!   calls).
//! - `env`: `config` (the task as data), `observation`, `privileged`, `reward`, `risk`,
//!   `state`, `single` (one robot: reset and step), `vec_env`, `scene`, `terrain`,
//!   `heightfield`, `snapshot` (resume codec), `bench`.
//! - `runner`: `train` (the `Trainer` loop), `setup` (fresh start or resume),
//!   `run_dir` (files and lock), `job` (what crosses MPI ranks), `status` (bar and log
//!   lines), `faults` (fault injection, divergence stop), `identity` (which run a
//!   checkpoint belongs to), `metrics`, `checkpoint_kinds` (a checkpoint's contents:
//!   full run state, actor-only, evaluation-only; save and load), `manifest` (shipped weights
//!   and their SHA-256), `resume` (exact-resume state),
//!   `adapt` (RMA phase 2 in a run), `dist` (MPI world), `scaling` (`rall bench
//!   scaling`: where an iteration's time goes, projected to more cores).
//! - `eval`: `tracking`, `scenario`, `ground`, `mjcf`, `rollout`, `ttf`, `platform`,
//!   `race`, `falls`, `severity`, `risk_calibration`, `report`, `cache` (rollout cache),
//!   `jobs` (parallel rollouts), `policy` (checkpoint and ONNX policies), `rall_graph`,
//!   `sidecar` (outside policies' sidecars), `commands` (the command-space safety map)
//!   and `commands_plot`.
//! - `experiment`: `spec`, `training`, `selection`, `final_policy`, `last_checkpoints`
//!   (benchmarks over each run's last K checkpoints, pooled), `benchmark` (the
//!   `Benchmark` trait), `evaluate`, `commands` (the command map as a benchmark),
//!   `commands_report` (its tables and README section), `command_plots` (its figures),
//!   `stats`, `pooled`, `curves`, `ladder`, `contrasts`, `verdicts` (pre-registered
//!   seed-level verdicts), `critic_tail`, `risk_signal`, `results` (`csv_tables`, `readme`,
//!   `write`), `plots`, `curve_plots`, `ship`, `status`, `clock`.
//! - `stats`: `seed_test` (Welch, permutation, Holm, power), `student_t`.
//! - `export`: `onnx` (the protobuf subset), `deploy` (the sidecar's deployment sections),
//!   `envelope` (the safe command envelope).
//! - `viz`: `episode`, `play`, `train`, `value`, `blueprint`, `sink`, `rrd`, `convert`.
//! - `cli`: one file per subcommand: `train`, `eval`, `experiment`, `export`, `play`,
//!   `checkpoint` (inspect, slim copies, manifest), `inspect` (a model file),
//!   `calibrate` (`rall calibrate-risk`), `bench` (env, comm, scaling).
//!
//! `unsafe` is refused everywhere but in `sim`, the audited GEMM, AMX and
//! AVX512-BF16 kernels (`learn::mat::gemm`, `learn::amx`, `learn::bf16_avx512`) and the
//! process's allocator ([`memory`]): each carries an explicit allow.
#![deny(unsafe_code)]

/// The allocator the `rall` binary and the benchmarks install
/// (`#[global_allocator]`): large buffers on transparent huge pages.
#[allow(unsafe_code)]
pub mod memory;

#[cfg(feature = "sim")]
pub mod env;
#[cfg(feature = "sim")]
pub mod eval;
#[cfg(feature = "sim")]
pub mod experiment;
#[cfg(feature = "sim")]
pub mod export;
#[cfg(feature = "sim")]
pub mod robot;
#[cfg(feature = "sim")]
#[allow(unsafe_code)]
pub mod sim;

pub mod fsio;
pub mod hash;
pub mod learn;
pub mod progress;
pub mod stats;

#[cfg(feature = "sim")]
pub mod cli;
#[cfg(feature = "sim")]
pub mod config;
#[cfg(feature = "sim")]
pub mod runner;
#[cfg(feature = "sim")]
pub mod viz;
