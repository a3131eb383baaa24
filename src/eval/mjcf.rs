//! Scenario MJCF as text: the robot file plus payload fragments, ground and a
//! keyframe extended to the scene's full `qpos`.
//!
//! The payload files in `mjcf/scenarios/` are compiled in (`include_str!`), so
//! the binary finds them from any directory; the robot comes from
//! `EnvConfig::robot_mjcf` as in training. Fragments are delimited in those files
//! by `<!-- @NAME-begin -->` / `<!-- @NAME-end -->` comments.

use crate::sim::{JointKind, Model, ObjKind, Result, SimError};

/// The Z1 arm (`mjcf/scenarios/z1_arm.xml`).
pub const Z1_ARM_XML: &str = include_str!("../../mjcf/scenarios/z1_arm.xml");
/// The container and ball (`mjcf/scenarios/ball_container.xml`).
pub const BALL_CONTAINER_XML: &str = include_str!("../../mjcf/scenarios/ball_container.xml");

fn invalid(msg: impl Into<String>) -> SimError {
    SimError::Invalid(msg.into())
}

/// The text between `<!-- @{name}-begin -->` and `<!-- @{name}-end -->`.
pub fn fragment<'a>(xml: &'a str, name: &str) -> Result<&'a str> {
    let begin = format!("<!-- @{name}-begin -->");
    let end = format!("<!-- @{name}-end -->");
    let b = xml
        .find(&begin)
        .ok_or_else(|| invalid(format!("payload MJCF has no {begin} marker")))?;
    let e = xml[b..]
        .find(&end)
        .ok_or_else(|| invalid(format!("payload MJCF has no {end} marker")))?;
    Ok(&xml[b + begin.len()..b + e])
}

/// Byte offset of the `</body>` that closes the body named `name`.
fn body_close(xml: &str, name: &str) -> Result<usize> {
    let open = format!("<body name=\"{name}\"");
    let start = xml
        .find(&open)
        .ok_or_else(|| invalid(format!("robot MJCF has no body named \"{name}\"")))?;
    let mut depth = 0usize;
    let mut i = start;
    while i < xml.len() {
        let rest = &xml[i..];
        if rest.starts_with("<!--") {
            i += rest.find("-->").map_or(rest.len(), |k| k + 3);
            continue;
        }
        if rest.starts_with("</body>") {
            depth -= 1;
            if depth == 0 {
                return Ok(i);
            }
            i += "</body>".len();
            continue;
        }
        if rest.starts_with("<body") {
            let tag_end = rest
                .find('>')
                .ok_or_else(|| invalid("unterminated <body> tag"))?;
            if !rest[..tag_end].ends_with('/') {
                depth += 1;
            }
            i += tag_end + 1;
            continue;
        }
        i += rest.chars().next().map_or(1, char::len_utf8);
    }
    Err(invalid(format!("body \"{name}\" is never closed")))
}

/// Removes every `<keyframe>...</keyframe>` section.
fn strip_keyframes(xml: &str) -> String {
    let mut out = String::with_capacity(xml.len());
    let mut rest = xml;
    while let Some(b) = rest.find("<keyframe") {
        out.push_str(&rest[..b]);
        match rest[b..].find("</keyframe>") {
            Some(e) => rest = &rest[b + e + "</keyframe>".len()..],
            None => {
                rest = "";
            }
        }
    }
    out.push_str(rest);
    out
}

/// What a scene adds to the robot's MJCF.
#[derive(Debug, Clone, Default)]
pub struct SceneParts {
    /// Bodies spliced at the end of the trunk body (welded payloads, the arm).
    pub trunk: String,
    /// Top-level `<asset>` content.
    pub asset: String,
    /// Top-level `<worldbody>` content (ground, obstacles, free payload bodies).
    pub world: String,
    /// Top-level `<actuator>` content.
    pub actuator: String,
}

/// The robot MJCF with `parts` spliced in, its keyframes removed, and `keyframe`
/// (a complete `<keyframe>` section) added when given.
pub fn scene_xml(robot_xml: &str, parts: &SceneParts, keyframe: Option<&str>) -> Result<String> {
    let robot = strip_keyframes(robot_xml);
    let close = body_close(&robot, "trunk")?;
    let mut xml = String::with_capacity(robot.len() + 4096);
    xml.push_str(&robot[..close]);
    xml.push_str(&parts.trunk);
    xml.push_str("\n    ");
    let rest = &robot[close..];
    let end = rest
        .rfind("</mujoco>")
        .ok_or_else(|| invalid("robot MJCF has no closing </mujoco> tag"))?;
    xml.push_str(&rest[..end]);
    for (tag, body) in [
        ("asset", &parts.asset),
        ("worldbody", &parts.world),
        ("actuator", &parts.actuator),
    ] {
        if !body.trim().is_empty() {
            xml.push_str(&format!("  <{tag}>\n{body}\n  </{tag}>\n"));
        }
    }
    if let Some(k) = keyframe {
        xml.push_str(k);
        xml.push('\n');
    }
    xml.push_str(&rest[end..]);
    Ok(xml)
}

/// Named joint positions: `(joint name, qpos values)` (7 for a free joint, 1 for a hinge).
pub type JointValues = Vec<(String, Vec<f64>)>;

/// The values of every joint of keyframe `key` of `model`, by joint name.
pub fn key_joint_values(model: &Model, key: &str) -> Result<JointValues> {
    let k = model.require_id(ObjKind::Key, key)?;
    let q = model.key_qpos(k);
    let mut out = Vec::with_capacity(model.njnt());
    for j in 0..model.njnt() {
        let n = joint_width(model.joint_kind(j));
        let a = model.joint_qpos_adr(j);
        out.push((
            model.name(ObjKind::Joint, j).to_string(),
            q[a..a + n].to_vec(),
        ));
    }
    Ok(out)
}

fn joint_width(kind: JointKind) -> usize {
    match kind {
        JointKind::Free => 7,
        JointKind::Ball => 4,
        JointKind::Slide | JointKind::Hinge => 1,
    }
}

/// A `<keyframe>` with one key `name` giving `model`'s full qpos from `values`
/// (by joint name). Refuses an unknown joint, a value of the wrong width, or a
/// joint left without a value.
pub fn keyframe_xml(model: &Model, name: &str, values: &JointValues) -> Result<String> {
    let nq = model.nq();
    let mut q: Vec<Option<f64>> = vec![None; nq];
    for (joint, v) in values {
        let j = model.require_id(ObjKind::Joint, joint)?;
        let n = joint_width(model.joint_kind(j));
        if v.len() != n {
            return Err(invalid(format!(
                "keyframe value of joint {joint} has {} numbers, the joint needs {n}",
                v.len()
            )));
        }
        let a = model.joint_qpos_adr(j);
        for (i, x) in v.iter().enumerate() {
            q[a + i] = Some(*x);
        }
    }
    for j in 0..model.njnt() {
        let a = model.joint_qpos_adr(j);
        if q[a].is_none() {
            return Err(invalid(format!(
                "keyframe {name}: no value for joint \"{}\"",
                model.name(ObjKind::Joint, j)
            )));
        }
    }
    let text: Vec<String> = q.iter().map(|x| format!("{}", x.unwrap_or(0.0))).collect();
    Ok(format!(
        "  <keyframe>\n    <key name=\"{name}\" qpos=\"{}\"/>\n  </keyframe>",
        text.join(" ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fragments_are_found() {
        assert!(fragment(Z1_ARM_XML, "trunk").unwrap().contains("z1_link06"));
        assert!(fragment(Z1_ARM_XML, "actuator")
            .unwrap()
            .contains("<position"));
        assert!(fragment(BALL_CONTAINER_XML, "world")
            .unwrap()
            .contains("payload_ball"));
        assert!(fragment(BALL_CONTAINER_XML, "nothing").is_err());
    }

    #[test]
    fn trunk_close_skips_nested_bodies_and_comments() {
        let xml = "<mujoco><worldbody><body name=\"trunk\"><!-- <body> --><body name=\"a\"><body name=\"b\"/></body></body><body name=\"x\"></body></worldbody></mujoco>";
        let c = body_close(xml, "trunk").unwrap();
        assert_eq!(&xml[c..c + 7], "</body>");
        assert!(xml[..c].ends_with("</body>"));
        assert!(xml[c + 7..].starts_with("<body name=\"x\">"));
    }

    #[test]
    fn keyframes_are_stripped() {
        let s = strip_keyframes("a<keyframe><key/></keyframe>b<keyframe>c</keyframe>d");
        assert_eq!(s, "abd");
    }
}
