//! `rall inspect MODEL.xml`: what is in a model, and does the robot stand.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

use crate::robot::{has_ground, standing_check, with_floor, ControlConfig, Robot};
use crate::sim::{Model, ObjKind};

#[derive(Debug, Args)]
pub struct InspectArgs {
    /// MJCF file to inspect (e.g. mjcf/aliengo.xml or mjcf/flat.xml).
    pub model: PathBuf,
    /// Simulated seconds of the standing check (0 skips it).
    #[arg(long, default_value_t = 10.0)]
    pub stand_seconds: f64,
}

pub fn run(args: &InspectArgs) -> Result<()> {
    let model = Model::from_xml_path(&args.model)?;
    println!(
        "model {}: MuJoCo {}",
        args.model.display(),
        crate::sim::mujoco_version()
    );
    print_model(&model);
    if args.stand_seconds <= 0.0 {
        return Ok(());
    }
    let model = if has_ground(&model) {
        model
    } else {
        println!("\n(no ground in the file: the standing check adds a flat plane)");
        let text = std::fs::read_to_string(&args.model)
            .with_context(|| format!("reading {}", args.model.display()))?;
        let scene = with_floor(&text).context("the file has no closing </mujoco> tag")?;
        Model::from_xml_str(&scene, &format!("{} + floor", args.model.display()))?
    };
    let control = ControlConfig::default();
    let mut robot = Robot::new(model, control.clone())
        .with_context(|| format!("{} is not an Aliengo-layout robot", args.model.display()))?;
    let report = standing_check(&mut robot, args.stand_seconds)?;
    println!(
        "\nstanding check: {:.1} s under PD (Kp {}, Kd {}, dt {} s) at keyframe '{}'",
        report.seconds,
        control.kp_nm_per_rad,
        control.kd_nm_s_per_rad,
        control.physics_dt_s,
        control.default_keyframe
    );
    println!(
        "  trunk height: min {:.3} m, max {:.3} m, final {:.3} m",
        report.min_height_m, report.max_height_m, report.final_height_m
    );
    println!("  feet in contact at the end: {}/4", report.feet_in_contact);
    if report.other_contacts.is_empty() {
        println!("  other robot contacts: none");
    } else {
        for (name, steps) in &report.other_contacts {
            println!("  other robot contact: {name} in {steps} steps");
        }
    }
    println!(
        "  max |torque|: {:.1} N m; MuJoCo warnings: {}",
        report.max_torque_nm, report.warnings
    );
    match &report.instability {
        Some(why) => println!("  UNSTABLE: {why}"),
        None => println!("  stable: yes"),
    }
    println!(
        "  holds the pose: {}",
        if report.holds_pose() { "yes" } else { "NO" }
    );
    Ok(())
}

fn print_model(m: &Model) {
    println!(
        "timestep {} s, total mass {:.3} kg",
        m.timestep_s(),
        m.total_mass_kg()
    );
    println!("\nbodies ({}):", m.nbody());
    for b in 0..m.nbody() {
        let parent = m.name(ObjKind::Body, m.body_parent(b));
        println!(
            "  {:>2} {:<12} mass {:>6.3} kg  parent {}",
            b,
            m.name(ObjKind::Body, b),
            m.body_mass_kg()[b],
            if b == 0 { "-" } else { parent }
        );
    }
    println!("\njoints ({}):", m.njnt());
    for j in 0..m.njnt() {
        let range = m.joint_range(j).map_or("unlimited".to_string(), |r| {
            format!("[{:.4}, {:.4}]", r[0], r[1])
        });
        println!(
            "  {:>2} {:<16} {:?} range {}",
            j,
            m.name(ObjKind::Joint, j),
            m.joint_kind(j),
            range
        );
    }
    println!("\nactuators ({}):", m.nu());
    for a in 0..m.nu() {
        let joint = m
            .actuator_joint(a)
            .map_or("-", |j| m.name(ObjKind::Joint, j));
        let range = m
            .actuator_ctrl_range(a)
            .map_or("unlimited".to_string(), |r| {
                format!("[{}, {}] N m", r[0], r[1])
            });
        println!(
            "  {:>2} {:<10} joint {:<16} torque {}",
            a,
            m.name(ObjKind::Actuator, a),
            joint,
            range
        );
    }
}
