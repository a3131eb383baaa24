//! Where an evaluation's time goes: each stage's wall-clock minutes and the
//! processor time the whole process spent in it (every thread), so that how
//! busy the cores were is visible beside how long it took. Processor time
//! barely depends on what else the machine runs, so it sizes an evaluation
//! even when it was measured on a shared machine.

use std::time::Instant;

use serde::{Deserialize, Serialize};

/// One stage (or a finer part of one) of an evaluation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PhaseTime {
    pub phase: String,
    pub wall_min: f64,
    /// Processor minutes of every thread of the process; `None` where the
    /// operating system does not report them.
    pub cpu_min: Option<f64>,
}

impl PhaseTime {
    /// "5.87 min, 9.80 core-min (1.67 cores busy)".
    pub fn show(&self) -> String {
        match self.cpu_min {
            Some(cpu) if self.wall_min > 0.0 => format!(
                "{:.2} min, {cpu:.2} core-min ({:.2} cores busy)",
                self.wall_min,
                cpu / self.wall_min
            ),
            _ => format!("{:.2} min", self.wall_min),
        }
    }
}

/// Processor seconds this process has used so far, user and system, over all of
/// its threads (Linux: `/proc/self/stat`, in the kernel's fixed 100 ticks per s).
pub fn process_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    cpu_s_from_stat(&stat)
}

/// utime + stime of a `/proc/<pid>/stat` line, in seconds. The command name
/// (field 2) may hold spaces and parentheses, so fields count from its last ')'.
fn cpu_s_from_stat(stat: &str) -> Option<f64> {
    const USER_HZ: f64 = 100.0;
    let after_name = &stat[stat.rfind(')')? + 1..];
    let fields: Vec<&str> = after_name.split_whitespace().collect();
    // fields 14 and 15 of the line; field 3 (the state) comes first here
    let utime: u64 = fields.get(14 - 3)?.parse().ok()?;
    let stime: u64 = fields.get(15 - 3)?.parse().ok()?;
    Some((utime + stime) as f64 / USER_HZ)
}

/// A point in both wall-clock and processor time.
#[derive(Clone, Copy)]
struct Mark {
    wall: Instant,
    cpu_s: Option<f64>,
}

impl Mark {
    fn now() -> Mark {
        Mark {
            wall: Instant::now(),
            cpu_s: process_cpu_s(),
        }
    }

    fn since(&self, phase: String) -> PhaseTime {
        let now = Mark::now();
        PhaseTime {
            phase,
            wall_min: now.wall.duration_since(self.wall).as_secs_f64() / 60.0,
            cpu_min: match (self.cpu_s, now.cpu_s) {
                (Some(a), Some(b)) => Some((b - a).max(0.0) / 60.0),
                _ => None,
            },
        }
    }
}

/// The evaluation's stages as they start (printed), and the time each took.
pub struct PhaseClock {
    start: Mark,
    stages: usize,
    started: usize,
    current: Option<(String, Mark)>,
    /// The stages ended so far, and any finer phases added.
    phases: Vec<PhaseTime>,
}

impl PhaseClock {
    pub fn new(stages: usize) -> PhaseClock {
        PhaseClock {
            start: Mark::now(),
            stages,
            started: 0,
            current: None,
            phases: Vec::new(),
        }
    }

    /// Ends the current stage and starts `what`.
    pub fn next(&mut self, what: &str) {
        self.end_current();
        let k = self.started + 1;
        eprintln!(
            "[eval {k}/{}] {what} ({:.1} min so far)",
            self.stages,
            self.total().wall_min
        );
        self.current = Some((what.to_string(), Mark::now()));
        self.started += 1;
    }

    /// Runs `f` inside the current stage and lists its time as `what`.
    pub fn time<R>(&mut self, what: String, f: impl FnOnce() -> R) -> R {
        let t = Mark::now();
        let out = f();
        self.phases.push(t.since(what));
        out
    }

    /// The time since the evaluation started.
    pub fn total(&self) -> PhaseTime {
        self.start.since("whole evaluation".into())
    }

    fn end_current(&mut self) {
        if let Some((what, t)) = self.current.take() {
            self.phases.push(t.since(what));
        }
    }

    /// The whole evaluation's time and each phase's.
    pub fn finish(mut self) -> (PhaseTime, Vec<PhaseTime>) {
        self.end_current();
        (self.total(), self.phases)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stat_lines_give_user_plus_system_seconds_whatever_the_command_name() {
        // pid (comm) state ppid pgrp sid tty tpgid flags minflt cminflt majflt cmajflt utime stime ...
        let line = "4242 (rall (eval) x) R 1 2 3 4 5 6 7 8 9 10 1234 566 0 0 20 0 3 0";
        assert_eq!(cpu_s_from_stat(line), Some(18.0));
        assert_eq!(cpu_s_from_stat("4242 (rall) R 1 2"), None);
        assert_eq!(cpu_s_from_stat("garbage"), None);
    }

    #[test]
    fn work_on_other_threads_counts_as_the_process_processor_time() {
        let Some(start_s) = process_cpu_s() else {
            return; // not Linux: the clock reports wall time alone
        };
        let mark = Mark::now();
        // two threads work until the process has used 0.4 s more (however long
        // that takes on a busy machine) while this thread waits; a clock that
        // counted this thread alone would never get there (60 s cap)
        let give_up = Instant::now() + std::time::Duration::from_secs(60);
        let spin = || {
            let mut x = 0u64;
            while process_cpu_s().unwrap() - start_s < 0.4 && Instant::now() < give_up {
                for _ in 0..100_000 {
                    x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
                }
            }
            std::hint::black_box(x);
        };
        std::thread::scope(|s| {
            s.spawn(spin);
            s.spawn(spin);
        });
        let p = mark.since("spin".into());
        let cpu_s = p.cpu_min.expect("processor time on Linux") * 60.0;
        // one tick (0.01 s) of rounding at each end
        assert!(cpu_s >= 0.38, "{cpu_s} s of processor time");
        assert!(p.show().contains("core-min"), "{}", p.show());
    }
}
