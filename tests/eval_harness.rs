//! The benchmark harness (TTF, platform drops, race track + meta controller).

use std::path::Path;

use rall::config::TrainConfig;
use rall::env::terrain::TerrainKind;
use rall::env::{EnvConfig, EpisodeEnd, ACT_DIM, OBS_DIM};
use rall::eval::platform::PlatformCell;
use rall::eval::report::write_outputs;
use rall::eval::ttf::ttf_cell;
use rall::eval::{
    build_scenario, evaluate_platform, evaluate_race, evaluate_ttf, time_to_fall, DropOutcome,
    DropWatch, FirstEpisode, GroundKind, Load, MetaArg, MetaConfig, MetaSwitch, NamedPolicy,
    PlatformOptions, RaceOptions, ScenarioParams, ScenarioRun, ScenarioSpec, TtfOptions,
};
use rall::learn::{CriticKind, Learner};
use rall::runner::{save_policy, Progress};

fn robot_mjcf() -> String {
    concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml").into()
}

/// A small untrained checkpoint, saved and loaded back as `rall eval` does.
fn tiny_policy(dir: &Path, name: &str, eta: f32, seed: u64) -> NamedPolicy {
    let mut c = TrainConfig::default();
    c.env.robot_mjcf = robot_mjcf();
    c.env.terrain.kind = TerrainKind::Flat;
    c.learner.critic = CriticKind::Iqn;
    c.learner.cvar_eta = Some(eta);
    c.learner.actor_hidden = vec![32, 32];
    c.learner.critic_hidden = vec![32, 32];
    c.learner.num_taus = 8;
    c.learner.num_target_taus = 8;
    c.learner.num_value_taus = 8;
    c.runner.seed = seed;
    let learner = Learner::new(OBS_DIM, ACT_DIM, &c.learner, seed).unwrap();
    let path = dir.join(format!("{name}.safetensors"));
    save_policy(&path, &learner, &c, &Progress::default()).unwrap();
    NamedPolicy::load(name, &path).unwrap()
}

fn ep(steps: usize, end: Option<EpisodeEnd>) -> FirstEpisode {
    FirstEpisode {
        steps,
        end,
        walked_m: steps as f64 / 100.0,
        commanded_m: 10.0,
        progress_m: steps as f64 / 100.0,
        strict_steps: steps,
    }
}

#[test]
fn ttf_arithmetic_on_scripted_episodes() {
    use EpisodeEnd::*;
    // Two seeds of three robots on 1000-step episodes.
    let seed_a = vec![ep(1000, Some(TimeOut)), ep(250, Some(Tilt)), ep(400, None)];
    let seed_b = vec![
        ep(1000, Some(TimeOut)),
        ep(1000, Some(TimeOut)),
        ep(100, Some(TrunkContact)),
    ];
    let spec = ScenarioSpec::new(Load::Ball, GroundKind::Rough, true);
    let c = ttf_cell(&spec, "RALL", &[seed_a, seed_b], 1000);
    assert!((c.ttf - 3750.0 / 6000.0).abs() < 1e-12, "ttf {}", c.ttf);
    assert!((c.ttf_per_seed[0] - 1650.0 / 3000.0).abs() < 1e-12);
    assert!((c.ttf_per_seed[1] - 2100.0 / 3000.0).abs() < 1e-12);
    assert_eq!((c.robots, c.falls, c.payload_falls), (6, 3, 1));
    assert_eq!(
        (c.terrain.as_str(), c.push, c.load),
        ("random", true, Load::Ball)
    );
    assert!((c.mean_steps - 625.0).abs() < 1e-12);
    assert!((c.walked_ratio - 37.5 / 60.0).abs() < 1e-12);
    assert_eq!(time_to_fall(&[1000; 4], 1000), 1.0);
    assert!((time_to_fall(&[0, 500], 1000) - 0.25).abs() < 1e-12);
}

#[test]
fn drop_watch_judges_scripted_trunk_paths() {
    // Edge at x = 0.8, trunk at 0.79 m on a 0.40 m platform, 100 settle steps.
    let w = || DropWatch::new(0.8, 0.79, 0.40, 100);
    let timeout = ep(400, Some(EpisodeEnd::TimeOut));
    // Standing still: never past the edge.
    let mut still = w();
    for s in 1..400 {
        still.observe(s, 0.0, 0.78);
    }
    assert_eq!(still.outcome(&timeout), DropOutcome::NotReached);
    assert_eq!(
        still.outcome(&ep(120, Some(EpisodeEnd::Tilt))),
        DropOutcome::FellBeforeDrop
    );
    // Walks off at step 50, lands, stands for the rest: success.
    let mut good = w();
    for s in 1..400 {
        let x = 0.6 + 0.005 * s as f64;
        good.observe(s, x, if x > 0.8 { 0.37 } else { 0.78 });
    }
    assert_eq!(good.dropped_at(), Some(41));
    assert_eq!(good.outcome(&timeout), DropOutcome::Success);
    // Drops at 41, falls at 90 (< 41 + 100): fell; falls at 200 (after the check): success.
    assert_eq!(
        good.outcome(&ep(90, Some(EpisodeEnd::Tilt))),
        DropOutcome::Success
    );
    let mut bad = w();
    for s in 1..90 {
        let x = 0.6 + 0.005 * s as f64;
        bad.observe(s, x, if x > 0.8 { 0.5 } else { 0.78 });
    }
    assert_eq!(
        bad.outcome(&ep(90, Some(EpisodeEnd::Tilt))),
        DropOutcome::Fell
    );
    assert_eq!(
        bad.outcome(&ep(90, None)),
        DropOutcome::Fell,
        "payload on the ground"
    );
    // Past the edge but hanging on it (trunk still up) at the check: not landed.
    let mut hang = w();
    for s in 1..400 {
        hang.observe(s, 0.85, 0.70);
    }
    assert_eq!(hang.outcome(&timeout), DropOutcome::NotLanded);
    // Off a side (x never past the edge, trunk came down): dropped.
    let mut side = w();
    for s in 1..400 {
        side.observe(s, 0.0, if s > 30 { 0.36 } else { 0.78 });
    }
    assert_eq!(side.outcome(&timeout), DropOutcome::Success);
    let cell = PlatformCell::from_outcomes(
        0.4,
        "p",
        &[
            DropOutcome::Success,
            DropOutcome::NotReached,
            DropOutcome::Fell,
            DropOutcome::Success,
        ],
    );
    assert_eq!(
        (cell.robots, cell.success, cell.not_reached, cell.fell),
        (4, 2, 1, 1)
    );
    assert_eq!(cell.success_pct, 50.0);
}

/// Zero actions (the PD holds the stance) on a 0.40 m platform; `shove(step, env)`
/// may disturb each robot.
fn platform_outcomes_of(shove: impl Fn(usize, &mut rall::env::Env)) -> Vec<DropOutcome> {
    let cfg = EnvConfig {
        robot_mjcf: robot_mjcf(),
        ..Default::default()
    };
    let mut p = ScenarioParams::default();
    p.platform.spawn_before_edge_m = 0.5;
    p.episode_length_s = Some(4.0);
    let spec = ScenarioSpec::new(Load::None, GroundKind::Platform { height_m: 0.40 }, false);
    let s = build_scenario(&spec, &cfg, &p, 0).unwrap();
    let geo = s.platform.unwrap();
    let n = 3;
    let mut run = ScenarioRun::new(&s, n, 2, 0).unwrap();
    let mut watch = vec![DropWatch::new(geo.edge_x_m, s.spawn_m[2], geo.height_m, 50); n];
    let mut first: Vec<Option<FirstEpisode>> = vec![None; n];
    let max = s.env.max_episode_steps();
    for step in 1..=max {
        for e in run.venv.envs_mut() {
            if first[e.index].is_none() {
                shove(step, e);
            }
        }
        for e in run.step(&vec![0.0; n * ACT_DIM]) {
            first[e.env_index].get_or_insert(ep(e.steps, Some(e.end)));
        }
        for (i, w) in watch.iter_mut().enumerate() {
            if first[i].is_none() {
                let p = run.env(i).robot().base_pos_m();
                w.observe(step, p[0], p[2]);
            }
        }
    }
    watch
        .iter()
        .zip(first)
        .map(|(w, f)| w.outcome(&f.unwrap_or(ep(max, Some(EpisodeEnd::TimeOut)))))
        .collect()
}

#[test]
fn platform_standing_still_is_not_reached_pushed_off_is_judged() {
    let still = platform_outcomes_of(|_, _| {});
    assert!(
        still.iter().all(|&o| o == DropOutcome::NotReached),
        "{still:?}"
    );
    // Shoved forward at 1.5 m/s: it tips over the edge and falls.
    let shoved = platform_outcomes_of(|s, e| {
        if s == 5 {
            e.kick_base_velocity([1.5, 0.0]);
        }
    });
    assert!(shoved.iter().all(|&o| o == DropOutcome::Fell), "{shoved:?}");
    // Carried 1 m forward, past the edge: it drops flat on its feet and stands.
    let carried = platform_outcomes_of(|s, e| {
        if s == 5 {
            let r = e.robot_mut();
            let a = r.layout.root_qpos_adr;
            r.data_mut().qpos_mut()[a] += 1.0;
            r.forward().unwrap();
        }
    });
    assert!(
        carried.iter().all(|&o| o == DropOutcome::Success),
        "{carried:?}"
    );
}

#[test]
fn meta_controller_switches_with_hysteresis() {
    // Threshold 1.0, back below 0.6.
    let mut m = MetaSwitch::new(1, 1.0, 0.4, 0);
    let iqr = [0.2, 0.9, 1.1, 0.9, 0.7, 0.5, 0.8, 1.0, 1.2, 0.1];
    let safe: Vec<bool> = iqr.iter().map(|&x| m.update(&[x])[0]).collect();
    assert_eq!(
        safe,
        [false, false, true, true, true, false, false, false, true, false]
    );
    assert_eq!((m.to_safe, m.to_risky), (2, 2));
    assert_eq!((m.safe_steps, m.steps), (4, 10));
    assert!((m.safe_fraction() - 0.4).abs() < 1e-12);
    // Without hysteresis it follows the threshold every step (0.9 after 1.1 switches back).
    let mut plain = MetaSwitch::new(1, 1.0, 0.0, 0);
    let s: Vec<bool> = iqr.iter().map(|&x| plain.update(&[x])[0]).collect();
    assert_eq!(
        s,
        [false, false, true, false, false, false, false, false, true, false]
    );
    assert_eq!((plain.to_safe, plain.to_risky), (2, 2));
    // A hold of 3 steps keeps SAFE even when the IQR drops at once.
    let mut hold = MetaSwitch::new(2, 1.0, 0.0, 3);
    let seq = [[2.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 2.0], [0.0, 0.0]];
    let s: Vec<Vec<bool>> = seq.iter().map(|x| hold.update(x).to_vec()).collect();
    assert_eq!(
        s,
        vec![
            vec![true, false],
            vec![true, false],
            vec![true, false],
            vec![false, true],
            vec![false, true]
        ]
    );
    hold.reset(1);
    assert_eq!(hold.on_safe(), &[false, false]);
    assert_eq!(hold.to_safe, 2);
}

#[test]
fn meta_argument_parses() {
    let m = MetaArg::parse("RISKY=a.safetensors,SAFE=RALL,THRESHOLD=0.8,hysteresis=0.2,HOLD=5")
        .unwrap();
    assert_eq!(
        (m.risky.as_str(), m.safe.as_str()),
        ("a.safetensors", "RALL")
    );
    assert_eq!((m.threshold, m.hysteresis, m.min_safe_steps), (0.8, 0.2, 5));
    assert!(
        MetaArg::parse("RISKY=a,SAFE=b").is_err(),
        "threshold required"
    );
    assert!(MetaArg::parse("RISKY=a,SAFE=b,THRESHOLD=x").is_err());
    assert!(MetaArg::parse("RISKY=a,SAFE=b,THRESHOLD=1,SPEED=3").is_err());
}

#[test]
fn eval_ttf_prints_a_complete_table_with_an_untrained_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let policies = vec![
        tiny_policy(dir.path(), "RALL", 0.5, 1),
        tiny_policy(dir.path(), "Baseline", 1.0, 2),
    ];
    let opts = TtfOptions {
        seeds: vec![0, 1],
        repeats: 2,
        threads: 2,
        // 2 s episodes with a push every 40 steps (held 20) so pushes happen.
        params: ScenarioParams {
            episode_length_s: Some(2.0),
            push_every_steps: 40,
            push_hold_steps: 20,
            ..ScenarioParams::default()
        },
        ..TtfOptions::default()
    };
    let mut lines = 0;
    let report = evaluate_ttf(&policies, &opts, |_| lines += 1).unwrap();
    assert_eq!(lines, 3 * 2 * 2 * 2);
    assert_eq!(report.cells.len(), 24);
    for c in &report.cells {
        assert_eq!((c.robots, c.episode_steps), (4, 100));
        assert!((0.0..=1.0).contains(&c.ttf) && c.ttf > 0.0, "{c:?}");
        assert_eq!(c.ttf_per_seed.len(), 2);
        assert!(c.walked_ratio.is_finite() && c.walked_ratio >= 0.0, "{c:?}");
    }
    let md = report.markdown();
    println!("{md}");
    let table: Vec<&str> = md.lines().filter(|l| l.starts_with('|')).collect();
    assert_eq!(table.len(), 2 + 3 * 2, "header, rule, 3 loads x 2 policies");
    assert_eq!(
        table[0],
        "| Load type | Policy | Flat, push False | Flat, push True | Random, push False | Random, push True |"
    );
    for (row, load) in [(2, "Ball"), (4, "Frozen arm"), (6, "Moving arm")] {
        assert!(
            table[row].starts_with(&format!("| {load} | RALL |")),
            "{}",
            table[row]
        );
        assert!(
            table[row + 1].starts_with("|  | Baseline |"),
            "{}",
            table[row + 1]
        );
    }
    for row in &table[2..] {
        let cells: Vec<&str> = row.trim_matches('|').split('|').map(str::trim).collect();
        assert_eq!(cells.len(), 6);
        for v in &cells[2..] {
            let x: f64 = v
                .trim_matches('*')
                .parse()
                .unwrap_or_else(|_| panic!("{row}"));
            assert!((0.0..=1.0).contains(&x));
        }
    }
    let out = dir.path().join("eval-results");
    let files = write_outputs(&out, "ttf", &md, &report.csv(), &report.json()).unwrap();
    assert_eq!(files.len(), 3);
    let csv = std::fs::read_to_string(out.join("ttf.csv")).unwrap();
    assert_eq!(csv.lines().count(), 25);
    assert!(csv.starts_with("load,terrain,push,policy,ttf,"));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("ttf.json")).unwrap()).unwrap();
    assert_eq!(json["cells"].as_array().unwrap().len(), 24);
    assert_eq!(json["policies"][1], "Baseline");
    // Same seeds, same numbers.
    let again = evaluate_ttf(&policies[..1], &opts, |_| {}).unwrap();
    let first: Vec<f64> = report
        .cells
        .iter()
        .filter(|c| c.policy == "RALL")
        .map(|c| c.ttf)
        .collect();
    let second: Vec<f64> = again.cells.iter().map(|c| c.ttf).collect();
    assert_eq!(first, second, "deterministic for a fixed seed set");
    // One thread or two (rollouts side by side), the same numbers to the bit.
    let one = TtfOptions {
        threads: 1,
        ..opts.clone()
    };
    let serial = evaluate_ttf(&policies, &one, |_| {}).unwrap();
    assert_eq!(serial.csv(), report.csv(), "thread count changed table I");
}

#[test]
fn platform_and_race_tables_with_untrained_checkpoints() {
    let dir = tempfile::tempdir().unwrap();
    let policies = vec![
        tiny_policy(dir.path(), "RALL", 0.5, 1),
        tiny_policy(dir.path(), "Risky", 1.0, 2),
    ];
    let opts = PlatformOptions {
        seeds: vec![0],
        repeats: 2,
        threads: 2,
        params: ScenarioParams {
            episode_length_s: Some(2.0),
            ..ScenarioParams::default()
        },
        ..PlatformOptions::default()
    };
    let p = evaluate_platform(&policies, &opts, |_| {}).unwrap();
    assert_eq!(p.cells.len(), 4);
    let one = PlatformOptions {
        threads: 1,
        ..opts.clone()
    };
    let serial = evaluate_platform(&policies, &one, |_| {}).unwrap();
    assert_eq!(serial.csv(), p.csv(), "thread count changed table II");
    let md = p.markdown();
    assert!(
        md.contains("| 0.40 m | RALL |") && md.contains("| 0.45 m | RALL |"),
        "{md}"
    );
    for c in &p.cells {
        let sum = c.success + c.fell + c.not_landed + c.fell_before_drop + c.not_reached;
        assert_eq!((c.robots, sum), (2, 2));
    }

    let mut params = ScenarioParams {
        episode_length_s: Some(1.0),
        ..ScenarioParams::default()
    };
    params.forward_mps = 0.8;
    let race = RaceOptions {
        agents: 3,
        episodes: 2,
        threads: 2,
        params,
        ..RaceOptions::default()
    };
    let meta = MetaConfig {
        name: "Meta".into(),
        risky: "Risky".into(),
        safe: "RALL".into(),
        threshold: 0.0,
        hysteresis: 0.0,
        min_safe_steps: 0,
    };
    let r = evaluate_race(&policies, std::slice::from_ref(&meta), &race, |_| {}).unwrap();
    assert_eq!(r.rows.len(), 3);
    for row in &r.rows {
        assert_eq!(row.episodes, 6, "{}", row.name);
        assert!(row.q25 <= row.q50 && row.q50 <= row.q75);
    }
    let log = r.rows[2].meta.as_ref().unwrap();
    assert!(log.safe_fraction >= 0.0 && log.safe_fraction <= 1.0);
    // Threshold 0: every step runs on SAFE; the IQR bins cover all robot-steps.
    assert!(log.safe_fraction > 0.99, "{log:?}");
    let binned: u64 = log.iqr_by_x.iter().map(|b| b.steps).sum();
    assert!(
        binned > 0 && binned == log.robot_steps,
        "{binned} of {}",
        log.robot_steps
    );
    assert!(log
        .iqr_by_x
        .iter()
        .all(|b| b.mean_iqr >= 0.0 && b.safe_fraction > 0.99));
    let one = RaceOptions {
        threads: 1,
        ..race.clone()
    };
    let serial = evaluate_race(&policies, std::slice::from_ref(&meta), &one, |_| {}).unwrap();
    assert_eq!(serial.csv(), r.csv(), "thread count changed the race");
    let md = r.markdown();
    println!("{md}");
    assert!(md.contains("| Meta |") && md.contains("switches to SAFE"));
}
