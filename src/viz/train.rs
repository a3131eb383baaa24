//! Recording a training run: the metrics of every iteration on an `iteration`
//! timeline, and every K iterations one short evaluation episode of the current
//! policy (the same entities as `rall play`, tagged with its iteration).

use anyhow::Result;
use rerun::RecordingStream;

use super::blueprint::{train_blueprint, TRAIN_APP_ID};
use super::episode::EpisodeLogger;
use super::play::{run_episode, ViewerEnv};
use super::sink::{finish_recording, open_recording, RerunTarget};
use super::value::{ValueProbe, DEFAULT_NUM_BARS};
use crate::config::TrainConfig;
use crate::env::reward::REWARD_TERM_NAMES;
use crate::learn::Learner;
use crate::runner::metrics::IterationRow;
use crate::runner::IterationObserver;

/// Settings of the training recording.
#[derive(Debug, Clone)]
pub struct TrainRecordingOptions {
    /// An evaluation episode every this many iterations (0 = never).
    pub eval_every: usize,
    /// Policy steps of an evaluation episode.
    pub eval_steps: usize,
}

impl Default for TrainRecordingOptions {
    fn default() -> Self {
        TrainRecordingOptions {
            eval_every: 50,
            eval_steps: 500,
        }
    }
}

struct Eval {
    venv: ViewerEnv,
    logger: EpisodeLogger,
}

/// The [`IterationObserver`] that logs a run to rerun.
pub struct TrainRecorder {
    rec: RecordingStream,
    cfg: TrainConfig,
    opts: TrainRecordingOptions,
    eval: Option<Eval>,
}

impl TrainRecorder {
    /// Opens the recording (failing fast without a viewer for spawn/connect).
    /// `cfg` is the run's config (its env is the evaluation env).
    pub fn open(
        target: &RerunTarget,
        run_name: &str,
        cfg: &TrainConfig,
        opts: TrainRecordingOptions,
    ) -> Result<Self> {
        let rec = open_recording(TRAIN_APP_ID, run_name, target, train_blueprint())?;
        Self::with_recording(rec, cfg, opts)
    }

    /// Uses an open recording (tests: a memory sink).
    pub fn with_recording(
        rec: RecordingStream,
        cfg: &TrainConfig,
        opts: TrainRecordingOptions,
    ) -> Result<Self> {
        let names =
            |ns: &[&str]| rerun::SeriesLines::new().with_names(ns.iter().map(|s| s.to_string()));
        rec.log_static("train/reward_terms", &names(&REWARD_TERM_NAMES))?;
        Ok(TrainRecorder {
            rec,
            cfg: cfg.clone(),
            opts,
            eval: None,
        })
    }

    fn log_metrics(&self, r: &IterationRow) -> Result<()> {
        let rec = &self.rec;
        rec.reset_time();
        rec.set_time_sequence("iteration", r.iteration as i64);
        let one = |path: &str, v: f64| rec.log(path, &rerun::Scalars::single(v));
        let e = r.episodes;
        let u = r.update;
        if e.episodes > 0 {
            rec.log(
                "train/reward_terms",
                &rerun::Scalars::new(e.reward_terms.iter().copied()),
            )?;
            one("train/episode/return", e.mean_return)?;
            one("train/episode/length", e.mean_length_steps)?;
            one(
                "train/episode/fall_fraction",
                e.falls as f64 / e.episodes as f64,
            )?;
            one("train/episode/lin_tracking", e.lin_tracking_score)?;
        }
        one("train/terrain_level", r.terrain_level)?;
        one("train/loss/policy", u.policy_loss as f64)?;
        one("train/loss/value", u.value_loss as f64)?;
        one("train/entropy", u.entropy as f64)?;
        one("train/approx_kl", u.approx_kl as f64)?;
        one("train/learning_rate", u.learning_rate as f64)?;
        one("train/std", u.mean_std as f64)?;
        one("train/risk_fired", r.risk_fired.iter().sum::<u64>() as f64)?;
        let elapsed = r.collect_s + r.learn_s;
        if elapsed > 0.0 {
            one("train/steps_per_s", r.iteration_env_steps as f64 / elapsed)?;
        }
        Ok(())
    }

    /// One evaluation episode of `learner`, tagged with `iteration`.
    pub fn evaluate(&mut self, learner: &Learner, iteration: usize) -> Result<()> {
        let env_seed = self.cfg.runner.seed ^ 0xE7A1;
        if self.eval.is_none() {
            let venv = ViewerEnv::new(&self.cfg.env, self.cfg.runner.seed, env_seed)?;
            let probe = ValueProbe::new(learner, DEFAULT_NUM_BARS);
            let logger = EpisodeLogger::new(
                self.rec.clone(),
                venv.env.robot(),
                venv.ground.clone(),
                probe,
            )?;
            self.eval = Some(Eval { venv, logger });
        }
        let ev = self.eval.as_mut().expect("built above");
        ev.venv.reseed(env_seed)?;
        ev.logger
            .set_extra_timeline("iteration", iteration as i64)?;
        let label = format!("evaluation at iteration {iteration}");
        run_episode(
            learner,
            &mut ev.venv.env,
            None,
            Some(&mut ev.logger),
            Some(self.opts.eval_steps),
            &label,
        )?;
        ev.logger.flush()
    }

    /// Waits for the evaluation episodes to be logged and closes the recording.
    pub fn finish(self) -> Result<()> {
        if let Some(ev) = self.eval {
            ev.logger.finish()?;
        }
        finish_recording(self.rec)
    }
}

impl IterationObserver for TrainRecorder {
    fn on_iteration(&mut self, row: &IterationRow, learner: &Learner) -> Result<()> {
        self.log_metrics(row)?;
        if self.opts.eval_every > 0 && row.iteration.is_multiple_of(self.opts.eval_every) {
            self.evaluate(learner, row.iteration)?;
        }
        Ok(())
    }
}
