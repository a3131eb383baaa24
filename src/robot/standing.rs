//! The standing check of `rall inspect`: hold the default pose under PD and report.

use super::{Part, Robot};
use crate::sim::{GeomShape, ObjKind, Result};

/// What happened while the robot stood under PD.
#[derive(Debug, Clone)]
pub struct StandingReport {
    pub seconds: f64,
    pub min_height_m: f64,
    pub max_height_m: f64,
    pub final_height_m: f64,
    /// Feet in contact with the ground at the end (of 4).
    pub feet_in_contact: usize,
    /// Names of non-foot robot geoms that touched anything, with the step count.
    pub other_contacts: Vec<(String, usize)>,
    /// Largest |joint torque| seen (N m).
    pub max_torque_nm: f64,
    /// MuJoCo warnings seen (total count).
    pub warnings: i64,
    /// Set when the physics became unstable (the message says why).
    pub instability: Option<String>,
}

impl StandingReport {
    /// The pass criteria the tests and `inspect` use: trunk between 0.30 and
    /// 0.45 m throughout, only the four feet touching, no warnings, stable.
    pub fn holds_pose(&self) -> bool {
        self.instability.is_none()
            && self.warnings == 0
            && self.min_height_m >= 0.30
            && self.max_height_m <= 0.45
            && self.other_contacts.is_empty()
            && self.feet_in_contact == 4
    }
}

/// Holds the default keyframe pose under PD for `seconds` of simulated time.
pub fn standing_check(robot: &mut Robot, seconds: f64) -> Result<StandingReport> {
    robot.reset_to_default()?;
    let target = robot.default_q_rad;
    let steps = (seconds / robot.control.physics_dt_s).round() as usize;
    let mut report = StandingReport {
        seconds,
        min_height_m: f64::INFINITY,
        max_height_m: f64::NEG_INFINITY,
        final_height_m: f64::NAN,
        feet_in_contact: 0,
        other_contacts: Vec::new(),
        max_torque_nm: 0.0,
        warnings: 0,
        instability: None,
    };
    let mut other: Vec<usize> = vec![0; robot.model().ngeom()];
    for _ in 0..steps {
        match robot.pd_substep(&target) {
            Ok(tau) => {
                report.max_torque_nm = tau.iter().fold(report.max_torque_nm, |m, t| m.max(t.abs()));
            }
            Err(e) => {
                report.instability = Some(e.to_string());
                break;
            }
        }
        let z = robot.base_pos_m()[2];
        if !z.is_finite() {
            report.instability = Some("non-finite trunk height".into());
            break;
        }
        report.min_height_m = report.min_height_m.min(z);
        report.max_height_m = report.max_height_m.max(z);
        for c in robot.data().contacts() {
            for g in [c.geom1, c.geom2] {
                if !matches!(robot.layout.geom_parts[g], Part::Foot(_) | Part::Other) {
                    other[g] += 1;
                }
            }
        }
    }
    report.final_height_m = robot.base_pos_m()[2];
    report.warnings = robot.data().warnings().total();
    let mut feet = [false; 4];
    for c in robot.data().contacts() {
        for g in [c.geom1, c.geom2] {
            if let Part::Foot(leg) = robot.layout.geom_parts[g] {
                feet[leg] = true;
            }
        }
    }
    report.feet_in_contact = feet.iter().filter(|&&f| f).count();
    report.other_contacts = other
        .iter()
        .enumerate()
        .filter(|(_, &n)| n > 0)
        .map(|(g, &n)| (robot.model().name(ObjKind::Geom, g).to_string(), n))
        .collect();
    Ok(report)
}

/// Whether the model has something to stand on (a plane or heightfield geom).
pub fn has_ground(model: &crate::sim::Model) -> bool {
    (0..model.ngeom()).any(|g| matches!(model.geom_shape(g), GeomShape::Plane | GeomShape::Hfield))
}

/// The MJCF text with a ground plane added (for robot-only files).
pub fn with_floor(xml: &str) -> Option<String> {
    let end = xml.rfind("</mujoco>")?;
    let floor = r#"  <worldbody>
    <geom name="floor" type="plane" size="0 0 0.05" contype="0" conaffinity="1" condim="3" friction="1.0 0.005 0.0001"/>
  </worldbody>
"#;
    Some(format!("{}{}{}", &xml[..end], floor, &xml[end..]))
}
