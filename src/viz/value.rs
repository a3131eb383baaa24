//! The critic's view of one state: the quantiles `Z_tau(s)` on a display grid,
//! their mean, the distorted value the actor follows and the IQR, from one critic
//! evaluation.

use crate::learn::{ActorCritic, Distortion, Learner};

/// Bars of the quantile chart by default.
pub const DEFAULT_NUM_BARS: usize = 32;

/// What the critic says about one observation.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ValueReading {
    /// `Z_tau(s)` at [`ValueProbe::taus`] (empty for the scalar critic).
    pub quantiles: Vec<f32>,
    /// Mean of the distribution on the display grid (scalar critic: `V(s)`).
    pub mean: f32,
    /// The value the actor follows: `CVaR_eta(Z(s))` (or the configured distortion);
    /// scalar critic: `V(s)`.
    pub distorted: f32,
    /// `Z_0.75(s) - Z_0.25(s)` (0 for the scalar critic).
    pub iqr: f32,
}

/// Evaluates the critic for the viewer.
///
/// For the IQN critic it asks for the display taus, the learner's own grid of the
/// distorted value and the two IQR taus in a single call, so the distorted value
/// and the IQR are exactly [`Learner::distorted_value`] and [`Learner::iqr`].
#[derive(Debug, Clone)]
pub struct ValueProbe {
    /// The critic has quantiles to chart (else it reads `V(s)` alone).
    quantiles: bool,
    taus: Vec<f32>,
    all_taus: Vec<f32>,
    num_value: usize,
    label: String,
}

impl ValueProbe {
    /// A probe with `num_bars` midpoint taus `(i + 1/2) / num_bars` for the chart.
    pub fn new(learner: &Learner, num_bars: usize) -> ValueProbe {
        let cfg = learner.config();
        let label = match cfg.distortion() {
            _ if !cfg.critic.has_quantiles() => "V".to_string(),
            Distortion::Cvar { eta } => format!("CVaR_{eta}"),
            Distortion::Wang { lambda } => format!("Wang_{lambda}"),
        };
        match cfg.critic.has_quantiles() {
            false => ValueProbe {
                quantiles: false,
                taus: vec![],
                all_taus: vec![],
                num_value: 0,
                label,
            },
            true => {
                let taus: Vec<f32> = (0..num_bars)
                    .map(|i| (i as f32 + 0.5) / num_bars as f32)
                    .collect();
                let value_taus = &learner.actor_critic().value_taus;
                let mut all = taus.clone();
                all.extend_from_slice(value_taus);
                all.extend_from_slice(&[0.25, 0.75]);
                ValueProbe {
                    quantiles: true,
                    taus,
                    all_taus: all,
                    num_value: value_taus.len(),
                    label,
                }
            }
        }
    }

    /// Abscissa of the bar chart (empty for the scalar critic).
    pub fn taus(&self) -> &[f32] {
        &self.taus
    }

    /// Name of the distorted value (`CVaR_0.5`, `Wang_-0.75`, `V`).
    pub fn label(&self) -> &str {
        &self.label
    }

    /// Reads the critic at one observation (`obs.len() == obs_dim`).
    pub fn read(&self, learner: &Learner, obs: &[f32]) -> ValueReading {
        self.read_batch(learner, obs)
            .pop()
            .expect("one observation")
    }

    /// Reads the critic at `n` observations (`obs`: `n x obs_dim`) in one call,
    /// much cheaper per observation than `n` calls.
    pub fn read_batch(&self, learner: &Learner, obs: &[f32]) -> Vec<ValueReading> {
        self.read_batch_ac(learner.actor_critic(), obs)
    }

    /// [`Self::read_batch`] on the networks alone (a snapshot another thread can own).
    pub fn read_batch_ac(&self, learner: &ActorCritic, obs: &[f32]) -> Vec<ValueReading> {
        if obs.is_empty() {
            return Vec::new();
        }
        match self.quantiles {
            false => learner
                .distorted_value(obs)
                .into_iter()
                .map(|v| ValueReading {
                    quantiles: vec![],
                    mean: v,
                    distorted: v,
                    iqr: 0.0,
                })
                .collect(),
            true => {
                let z = learner.value_quantiles(obs, &self.all_taus);
                let nb = self.taus.len();
                z.chunks_exact(self.all_taus.len())
                    .map(|row| {
                        let (bars, rest) = row.split_at(nb);
                        let (value, iqr) = rest.split_at(self.num_value);
                        ValueReading {
                            quantiles: bars.to_vec(),
                            mean: if nb > 0 {
                                bars.iter().sum::<f32>() / nb as f32
                            } else {
                                f32::NAN
                            },
                            distorted: value.iter().sum::<f32>() / self.num_value.max(1) as f32,
                            iqr: iqr[1] - iqr[0],
                        }
                    })
                    .collect()
            }
        }
    }
}
