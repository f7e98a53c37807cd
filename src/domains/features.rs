//! What each observation and action entry of prac's domains is, by name and unit: the contract a
//! robot team needs beside the sizes (`PolicyInfo`, `prac export-onnx`'s `prac.json`).
//!
//! The robots observe as PyBullet's locomotion tasks do: the torso's height above its start, the
//! sine and cosine of the angle to the target, its velocity in the robot's heading frame (scaled
//! by 0.3), roll and pitch, then each joint's position (its range mapped to [-1, 1]) and speed
//! (scaled by 0.1), then each foot's contact. Joint and foot names are those of the MuJoCo
//! models PyBullet loads (hopper.xml, walker2d.xml, half_cheetah.xml, ant.xml,
//! humanoid_symmetric.xml), in the order the robots in `robots/` build them.

pub use crate::manifest::{Feature, Features};

fn feature(name: impl Into<String>, unit: &str) -> Feature {
    Feature {
        name: name.into(),
        unit: unit.to_string(),
    }
}

/// The features of a robot with these joints (each a motor) and feet.
fn robot(joints: &[&str], feet: &[&str]) -> Features {
    let mut observation = vec![
        feature("torso_height_above_start", "m"),
        feature("sin_angle_to_target", "1"),
        feature("cos_angle_to_target", "1"),
        feature("forward_velocity", "0.3 m/s"),
        feature("sideways_velocity", "0.3 m/s"),
        feature("vertical_velocity", "0.3 m/s"),
        feature("roll", "rad"),
        feature("pitch", "rad"),
    ];
    for joint in joints {
        observation.push(feature(
            format!("{joint}_position"),
            "joint range mapped to [-1, 1]",
        ));
        observation.push(feature(format!("{joint}_speed"), "0.1 rad/s"));
    }
    for foot in feet {
        observation.push(feature(format!("{foot}_contact"), "1 touching, 0 not"));
    }
    let action = joints
        .iter()
        .map(|joint| feature(format!("{joint}_torque"), "fraction of the motor's torque"))
        .collect();
    Features {
        observation,
        action,
    }
}

/// The features of one of prac's domains; None for a domain prac does not know.
pub fn features(domain: &str) -> Option<Features> {
    Some(match domain {
        "pendulum" => Features {
            observation: vec![
                feature("cos_theta", "1"),
                feature("sin_theta", "1"),
                feature("theta_velocity", "rad/s"),
            ],
            action: vec![feature("torque", "N m")],
        },
        "lander" => Features {
            observation: vec![
                feature("x", "scaled as gymnasium's LunarLander"),
                feature("y", "scaled as gymnasium's LunarLander"),
                feature("x_velocity", "scaled as gymnasium's LunarLander"),
                feature("y_velocity", "scaled as gymnasium's LunarLander"),
                feature("angle", "rad"),
                feature("angular_velocity", "0.4 rad/s"),
                feature("left_leg_contact", "1 touching, 0 not"),
                feature("right_leg_contact", "1 touching, 0 not"),
            ],
            action: vec![
                feature("main_engine", "off below 0, 50 % to 100 % power over 0..1"),
                feature(
                    "side_engines",
                    "off within +-0.5, else its sign picks the engine, 50 % to 100 % power",
                ),
            ],
        },
        "hopper" => robot(&["thigh", "leg", "foot"], &["foot"]),
        "walker" => robot(
            &[
                "thigh",
                "leg",
                "foot",
                "thigh_left",
                "leg_left",
                "foot_left",
            ],
            &["foot", "foot_left"],
        ),
        "cheetah" => robot(
            &["bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot"],
            &["ffoot", "fshin", "fthigh", "bfoot", "bshin", "bthigh"],
        ),
        "ant" => robot(
            &[
                "hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3", "hip_4", "ankle_4",
            ],
            &[
                "front_left_foot",
                "front_right_foot",
                "left_back_foot",
                "right_back_foot",
            ],
        ),
        "humanoid" => robot(
            &[
                "abdomen_z",
                "abdomen_y",
                "abdomen_x",
                "right_hip_x",
                "right_hip_z",
                "right_hip_y",
                "right_knee",
                "left_hip_x",
                "left_hip_z",
                "left_hip_y",
                "left_knee",
                "right_shoulder1",
                "right_shoulder2",
                "right_elbow",
                "left_shoulder1",
                "left_shoulder2",
                "left_elbow",
            ],
            &["right_foot", "left_foot"],
        ),
        _ => return None,
    })
}
