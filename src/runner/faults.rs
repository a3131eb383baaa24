//! Fault injection for the tests of the divergence checks, and the check that
//! stops a run whose update produced non-finite numbers.
//!
//! `RALL_FAULT_NAN=<iteration>` makes one weight NaN after that iteration's
//! update; `RALL_FAULT_PERTURB=<rank>:<iteration>` asks that rank to nudge one
//! weight after that iteration's update (the ranks then diverge).

use std::path::Path;

use anyhow::Result;

use crate::learn::{Learner, UpdateStats};

/// The faults this process was asked to inject (none in a normal run).
pub(super) struct FaultHooks {
    /// `(rank, iteration)` of `RALL_FAULT_PERTURB`.
    perturb: Option<(usize, usize)>,
    /// Iteration of `RALL_FAULT_NAN`.
    nan: Option<usize>,
}

impl FaultHooks {
    /// Reads the fault variables; a malformed one is an error.
    pub(super) fn from_env() -> Result<FaultHooks> {
        Ok(FaultHooks {
            perturb: divergence_fault()?,
            nan: nan_fault()?,
        })
    }

    /// After the update of `iteration` (1-based): injects the NaN fault, stops a
    /// run that diverged (naming `last_good`), then injects the perturbation.
    pub(super) fn after_update(
        &self,
        learner: &mut Learner,
        update: &UpdateStats,
        rank: usize,
        iteration: usize,
        last_good: Option<&Path>,
    ) -> Result<()> {
        if self.nan == Some(iteration) {
            poison_one_weight(learner)?;
        }
        ensure_finite(update, learner, iteration, last_good)?;
        if self.perturb == Some((rank, iteration)) {
            nudge_one_weight(learner)?;
        }
        Ok(())
    }
}

/// `RALL_FAULT_PERTURB=<rank>:<iteration>`, if set.
fn divergence_fault() -> Result<Option<(usize, usize)>> {
    let Ok(spec) = std::env::var("RALL_FAULT_PERTURB") else {
        return Ok(None);
    };
    let target = spec
        .split_once(':')
        .and_then(|(r, i)| Some((r.parse::<usize>().ok()?, i.parse::<usize>().ok()?)));
    match target {
        Some(t) => Ok(Some(t)),
        None => anyhow::bail!("RALL_FAULT_PERTURB={spec:?}: expected <rank>:<iteration>"),
    }
}

/// `RALL_FAULT_NAN=<iteration>`, if set.
fn nan_fault() -> Result<Option<usize>> {
    match std::env::var("RALL_FAULT_NAN") {
        Err(_) => Ok(None),
        Ok(v) => v
            .parse()
            .map(Some)
            .map_err(|_| anyhow::anyhow!("RALL_FAULT_NAN={v:?}: expected an iteration")),
    }
}

/// Sets the first weight to NaN (the injected numerical failure).
fn poison_one_weight(learner: &mut Learner) -> Result<()> {
    let mut state = learner.state();
    state[0].data[0] = f32::NAN;
    learner.load_state(&state)
}

/// Adds 1e-3 to the first weight (the injected divergence).
fn nudge_one_weight(learner: &mut Learner) -> Result<()> {
    let mut state = learner.state();
    state[0].data[0] += 1e-3;
    learner.load_state(&state)
}

/// Stops a run whose update produced a non-finite loss or weights, instead of
/// training (and checkpointing) garbage to the end.
fn ensure_finite(
    u: &UpdateStats,
    learner: &Learner,
    iteration: usize,
    last_good: Option<&Path>,
) -> Result<()> {
    let losses_ok =
        u.policy_loss.is_finite() && u.value_loss.is_finite() && u.grad_norm.is_finite();
    let weights_ok = learner
        .state()
        .iter()
        .all(|t| t.data.iter().all(|v| v.is_finite()));
    if losses_ok && weights_ok {
        return Ok(());
    }
    anyhow::bail!(
        "training diverged at iteration {iteration}: policy loss {}, value loss {}, gradient norm {}{} (check observation scales, reward weights and the physics dt); {}",
        u.policy_loss,
        u.value_loss,
        u.grad_norm,
        if weights_ok { "" } else { ", non-finite weights" },
        match last_good {
            Some(p) => format!("nothing was saved after the last good checkpoint {}", p.display()),
            None => "no checkpoint was written before it".into(),
        }
    )
}
