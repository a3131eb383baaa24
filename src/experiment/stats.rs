//! Percentile bootstrap over robots (or agents): resample the units with
//! replacement, recompute the statistic, take the two-sided quantiles.
//! Seeded, so the same data give the same interval. The definitions live in
//! [`crate::stats`], shared with the evaluation.

pub use crate::stats::{
    bootstrap, bootstrap_strata, cell_seed, mean, percentile, quantile, Estimate,
};
