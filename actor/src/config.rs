//! The world's config: every number of `shared/feeding.md`, with its defaults.
//!
//! A person's profile (preference weights, body, impairment, comfort threshold) is part of
//! it: different profiles are different people.

use serde::{Deserialize, Serialize};

/// The preference weights `w` of r_H = w . [C_d, C_e, C_v, C_f, C_hf, C_fd, C_fdv].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PreferenceWeights {
    /// Distance of the spoon to the mouth (C_d = -d).
    pub distance: f32,
    /// Food eaten this step (C_e).
    pub eaten: f32,
    /// End-effector speed (C_v = -speed).
    pub velocity: f32,
    /// Contact force of robot and spoon on the person (C_f).
    pub force: f32,
    /// Hard spoon force (C_hf = -F_spoon when F_spoon >= the threshold).
    pub high_force: f32,
    /// Food hitting the person (C_fd).
    pub food_hit: f32,
    /// Speed of food reaching the mouth (C_fdv).
    pub food_velocity: f32,
}

impl PreferenceWeights {
    /// The weights in term order.
    pub fn as_array(&self) -> [f32; 7] {
        [
            self.distance,
            self.eaten,
            self.velocity,
            self.force,
            self.high_force,
            self.food_hit,
            self.food_velocity,
        ]
    }
}

/// Which body the person has.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum BodySize {
    /// Drawn 50/50 at every reset (as the original).
    Random,
    /// The larger body (chest at z 0.89).
    Large,
    /// The smaller body (chest at z 0.86).
    Small,
}

/// The person's impairment.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Impairment {
    /// Drawn uniformly from the four below at every reset (as the original).
    Random,
    None,
    /// Head limits scaled by U(limits_scale_min, 1).
    Limits,
    /// No effect on a person who does not act.
    Weakness,
    /// The head shakes about its resting angles.
    Tremor,
}

/// A person's taste beyond the seven terms: what they mind that no comfort feature names
/// (the learner sees neither these terms nor their weights; only the labels carry them).
/// Each adds to r_H, so to the ground truth every scripted teacher judges by. All zero (the
/// default): no such taste.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Taste {
    /// Where the spoon should come from: a direction in the head frame, from the mouth
    /// towards where the person wants to see the spoon arrive (`[0, -1, 0]`: straight in
    /// front of the face; `[0, -0.7, -0.7]`: from below). Need not be unit length.
    pub approach: [f32; 3],
    /// Weight of C_ap = -(1 - cos of the angle between spoon - mouth and `approach`), at
    /// every step the spoon is on its way in: nearer the mouth than `approach_radius`, and
    /// not yet as near as `approach_inner`, where the direction stops meaning anything
    /// (0: no such taste).
    pub approach_weight: f32,
    /// How near the mouth (m) the approach starts to count.
    pub approach_radius: f32,
    /// How near the mouth (m) it stops counting (the spoon has arrived).
    pub approach_inner: f32,
    /// Weight of C_bite = -1 at every step in which food reaches the mouth after a step in
    /// which none did: a person who wants fewer, bigger bites (0: no such taste).
    pub bite_weight: f32,
}

impl Default for Taste {
    fn default() -> Self {
        Self {
            approach: [0.0, -1.0, 0.0],
            approach_weight: 0.0,
            approach_radius: 0.15,
            approach_inner: 0.04,
            bite_weight: 0.0,
        }
    }
}

impl Taste {
    /// The kinds of taste this person has, by name (`approach`, `bites`), none for most.
    pub fn kinds(&self) -> Vec<&'static str> {
        let mut k = Vec::new();
        if self.approach_weight != 0.0 {
            k.push("approach");
        }
        if self.bite_weight != 0.0 {
            k.push("bites");
        }
        k
    }
}

/// A person: preference weights, body, impairment, comfort threshold and taste.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Profile {
    /// Name of the profile ("paper", "assistive-gym" or a user's own).
    pub name: String,
    /// Preference weights w.
    pub weights: PreferenceWeights,
    /// Body size.
    pub body: BodySize,
    /// Impairment.
    pub impairment: Impairment,
    /// Spoon force (N) from which C_hf counts.
    pub high_force_threshold: f32,
    /// Taste no comfort feature names (none by default).
    #[serde(default)]
    pub taste: Taste,
}

impl Profile {
    /// The paper's person (Eq. 6 weights), the default.
    pub fn paper() -> Self {
        Self {
            name: "paper".into(),
            weights: PreferenceWeights {
                distance: 0.5,
                eaten: 0.5,
                velocity: 0.25,
                force: 0.3,
                high_force: 0.1,
                food_hit: 2.5,
                food_velocity: 10.0,
            },
            body: BodySize::Random,
            impairment: Impairment::Random,
            high_force_threshold: 10.0,
            taste: Taste::default(),
        }
    }

    /// Stock Assistive-Gym's person: no C_d or C_e term.
    pub fn assistive_gym() -> Self {
        Self {
            name: "assistive-gym".into(),
            weights: PreferenceWeights {
                distance: 0.0,
                eaten: 0.0,
                velocity: 0.25,
                force: 0.01,
                high_force: 0.05,
                food_hit: 1.0,
                food_velocity: 1.0,
            },
            ..Self::paper()
        }
    }

    /// A shipped profile by name.
    pub fn by_name(name: &str) -> Result<Self, ConfigError> {
        match name {
            "paper" => Ok(Self::paper()),
            "assistive-gym" => Ok(Self::assistive_gym()),
            other => Err(ConfigError::invalid(
                "profile",
                other,
                "known profiles are paper and assistive-gym",
            )),
        }
    }
}

/// Where the robot base stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum BasePlacement {
    /// Sampled at every reset, kept when IK reaches the start pose and the mouth (original).
    Random,
    /// The nominal base (-0.85, -0.2, 0.925), yaw 0.
    Nominal,
}

/// The feeding world. Lengths in metres, angles in radians unless the name says degrees.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WorldConfig {
    /// The person.
    pub profile: Profile,
    /// Physics substep (s).
    pub substep_dt: f32,
    /// Physics substeps per env step (10 Hz control at the defaults).
    pub substeps: u32,
    /// Env steps per episode (the time limit).
    pub episode_steps: u32,
    /// Substeps the food settles on the spoon at reset, before the first observation.
    pub settle_substeps: u32,
    /// Iterations (internal substeps) of rapier's contact solver per physics substep.
    pub solver_iterations: u32,
    /// Gravity (m/s^2, along -z) on the food.
    pub gravity: f32,

    /// Robot base placement.
    pub base: BasePlacement,
    /// Nominal base position.
    pub base_nominal: [f32; 3],
    /// Random base: x offset range added to the nominal x.
    pub base_x_range: [f32; 2],
    /// Random base: y offset range added to the nominal y.
    pub base_y_range: [f32; 2],
    /// Random base: yaw range (degrees).
    pub base_yaw_deg_range: [f32; 2],
    /// Base samples tried before a reset fails.
    pub base_tries: u32,
    /// IK rest poses tried per base sample.
    pub ik_tries: u32,

    /// Start pose of the end effector (world), before the random offset.
    pub start_ee: [f32; 3],
    /// Half-width of the uniform offset of the start pose on each axis.
    pub start_ee_noise: f32,
    /// Start orientation of the end effector (roll, pitch, yaw).
    pub start_ee_rpy: [f32; 3],
    /// IK success: position error below this (m).
    pub ik_pos_tol: f32,
    /// IK success: quaternion difference norm below this.
    pub ik_rot_tol: f32,

    /// Action scale: joint targets are q + action_scale * a.
    pub action_scale: f32,
    /// Motor position gain (the original's PyBullet gain).
    pub motor_gain: f32,
    /// Motor torque cap per joint (N m).
    pub motor_max_force: f32,
    /// Joint damping (N m s/rad).
    pub joint_damping: f32,
    /// Mass of the spoon (kg), carried at the end of the arm.
    pub spoon_mass: f32,
    /// Rotational inertia of the spoon about its origin (kg m^2, isotropic).
    pub spoon_inertia: f32,
    /// Effective inertia of each joint (kg m^2) without the spoon, fitted so that the
    /// joints respond to actions as the original's do.
    pub joint_inertia: [f32; 7],
    /// Fraction of a penetration removed per substep by the contact solver.
    pub contact_erp: f32,
    /// Penetration allowed before the contact solver pushes back (m).
    pub contact_slop: f32,

    /// Number of food particles.
    pub food_count: u32,
    /// Food radius (m).
    pub food_radius: f32,
    /// Food mass (kg).
    pub food_mass: f32,
    /// Food friction coefficient.
    pub food_friction: f32,
    /// A particle this close to the mouth target is eaten (m).
    pub eat_distance: f32,
    /// A particle this far from the spoon (surface to surface) is spilled (m).
    pub spill_distance: f32,
    /// Fraction of the food that must be eaten for success.
    pub success_fraction: f32,

    /// Spoon bowl: inner half-width (x), inner half-length (z), floor thickness.
    pub spoon_bowl_half: [f32; 3],
    /// Spoon rim height above the bowl floor at the sides, the back and the tip.
    pub spoon_rim_height: [f32; 3],
    /// Spoon rim wall thickness.
    pub spoon_rim_thickness: f32,
    /// Spoon handle length.
    pub spoon_handle_length: f32,

    /// Head angles at reset are drawn from U(-this, this) per axis (degrees).
    pub head_angle_deg: f32,
    /// Head joint limits (x, y, z, degrees).
    pub head_limit_deg: [f32; 3],
    /// Impairment "limits": head limits scaled by U(this, 1).
    pub limits_scale_min: f32,
    /// Impairment "tremor": amplitude drawn from U(-this, this) per head joint (degrees).
    pub tremor_deg: f32,
    /// Head motor gain (tremor).
    pub head_motor_gain: f32,

    /// Bowl on the table: centre before its random offset.
    pub bowl: [f32; 3],
    /// Bowl offset half-width in x and y.
    pub bowl_noise: f32,
    /// Table top height.
    pub table_height: f32,
    /// Table top centre (x, y).
    pub table_centre: [f32; 2],
    /// Table top size (x, y).
    pub table_size: [f32; 2],
}

impl Default for WorldConfig {
    fn default() -> Self {
        Self {
            profile: Profile::paper(),
            substep_dt: 0.02,
            substeps: 5,
            episode_steps: 200,
            settle_substeps: 25,
            solver_iterations: 2,
            gravity: 9.81,
            base: BasePlacement::Random,
            base_nominal: [-0.85, -0.2, 0.925],
            base_x_range: [-0.5, 0.0],
            base_y_range: [-0.5, 0.5],
            base_yaw_deg_range: [-30.0, 30.0],
            base_tries: 50,
            ik_tries: 8,
            start_ee: [-0.15, -0.65, 1.15],
            start_ee_noise: 0.05,
            start_ee_rpy: [
                std::f32::consts::FRAC_PI_2,
                0.0,
                std::f32::consts::FRAC_PI_2,
            ],
            ik_pos_tol: 0.03,
            ik_rot_tol: 0.03,
            action_scale: 0.25,
            motor_gain: 0.025,
            motor_max_force: 1.0,
            joint_damping: 0.7,
            spoon_mass: 1.0,
            spoon_inertia: 0.0025,
            joint_inertia: [1.1, 0.6, 0.3, 1.0, 0.005, 0.005, 0.02],
            contact_erp: 0.2,
            contact_slop: 0.001,
            food_count: 8,
            food_radius: 0.005,
            food_mass: 0.001,
            food_friction: 0.5,
            eat_distance: 0.03,
            spill_distance: 0.10,
            success_fraction: 0.75,
            spoon_bowl_half: [0.0179, 0.029, 0.006],
            spoon_rim_height: [0.011, 0.008, 0.014],
            spoon_rim_thickness: 0.004,
            spoon_handle_length: 0.11,
            head_angle_deg: 30.0,
            head_limit_deg: [50.0, 34.0, 70.0],
            limits_scale_min: 0.5,
            tremor_deg: 20.0,
            head_motor_gain: 0.025,
            bowl: [-0.15, -0.65, 0.75],
            bowl_noise: 0.05,
            table_height: 0.725,
            table_centre: [0.25, -1.0],
            table_size: [1.5, 1.0],
        }
    }
}

/// A config value that cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("invalid {field} = {value}: {reason}")]
pub struct ConfigError {
    pub field: String,
    pub value: String,
    pub reason: String,
}

impl ConfigError {
    pub fn invalid(field: &str, value: impl std::fmt::Display, reason: &str) -> Self {
        Self {
            field: field.into(),
            value: value.to_string(),
            reason: reason.into(),
        }
    }
}

impl WorldConfig {
    /// The world used by tests: nominal base, larger body, no impairment.
    pub fn fixed() -> Self {
        Self {
            base: BasePlacement::Nominal,
            profile: Profile {
                body: BodySize::Large,
                impairment: Impairment::None,
                ..Profile::paper()
            },
            ..Self::default()
        }
    }

    /// Read a config from JSON; fields left out keep their defaults.
    pub fn from_json(text: &str) -> Result<Self, ConfigError> {
        let cfg: Self = serde_json::from_str(text)
            .map_err(|e| ConfigError::invalid("world config", "(json)", &e.to_string()))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Physical time of one env step.
    pub fn control_dt(&self) -> f32 {
        self.substep_dt * self.substeps as f32
    }

    /// Food particles that must be eaten for success.
    pub fn food_for_success(&self) -> u32 {
        (self.success_fraction * self.food_count as f32).ceil() as u32
    }

    /// Check every field that could break the world; the error names the field and value.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.check_counts()?;
        self.check_food()?;
        self.check_arm()?;
        self.check_spoon()?;
        self.check_scene()?;
        self.check_profile()
    }

    /// The counts: food, substeps, iterations, steps, tries.
    fn check_counts(&self) -> Result<(), ConfigError> {
        if self.food_count == 0 {
            return Err(ConfigError::invalid(
                "food_count",
                0,
                "the world needs at least one food particle",
            ));
        }
        if self.food_count > 64 {
            return Err(ConfigError::invalid(
                "food_count",
                self.food_count,
                "at most 64 particles fit on the spoon",
            ));
        }
        for (field, v, max) in [
            ("substeps", self.substeps, 1_000),
            ("solver_iterations", self.solver_iterations, 100),
            ("episode_steps", self.episode_steps, 100_000),
            ("base_tries", self.base_tries, 10_000),
            ("ik_tries", self.ik_tries, 1_000),
        ] {
            if v == 0 || v > max {
                return Err(ConfigError::invalid(
                    field,
                    v,
                    &format!("must be in 1..={max}"),
                ));
            }
        }
        if self.settle_substeps > 100_000 {
            return Err(ConfigError::invalid(
                "settle_substeps",
                self.settle_substeps,
                "must be at most 100000",
            ));
        }
        Ok(())
    }

    /// The food and gravity.
    fn check_food(&self) -> Result<(), ConfigError> {
        positive("substep_dt", self.substep_dt)?;
        positive("food_radius", self.food_radius)?;
        positive("food_mass", self.food_mass)?;
        non_negative("food_friction", self.food_friction)?;
        non_negative("gravity", self.gravity)?;
        positive("eat_distance", self.eat_distance)?;
        positive("spill_distance", self.spill_distance)?;
        if !(self.success_fraction > 0.0 && self.success_fraction <= 1.0) {
            return Err(ConfigError::invalid(
                "success_fraction",
                self.success_fraction,
                "must be in (0, 1]",
            ));
        }
        Ok(())
    }

    /// The arm: its motors, inertias, the spoon's mass and the contacts.
    fn check_arm(&self) -> Result<(), ConfigError> {
        positive("action_scale", self.action_scale)?;
        positive("motor_gain", self.motor_gain)?;
        positive("motor_max_force", self.motor_max_force)?;
        non_negative("joint_damping", self.joint_damping)?;
        // NOTE: bounded so that the arm's mass matrix is always well conditioned.
        for (i, &m) in self.joint_inertia.iter().enumerate() {
            if !(1e-4..=1e3).contains(&m) {
                return Err(ConfigError::invalid(
                    &format!("joint_inertia[{i}]"),
                    m,
                    "must be in [1e-4, 1e3] kg m^2",
                ));
            }
        }
        if !(0.0..=100.0).contains(&self.spoon_mass) {
            return Err(ConfigError::invalid(
                "spoon_mass",
                self.spoon_mass,
                "must be in [0, 100] kg",
            ));
        }
        if !(0.0..=10.0).contains(&self.spoon_inertia) {
            return Err(ConfigError::invalid(
                "spoon_inertia",
                self.spoon_inertia,
                "must be in [0, 10] kg m^2",
            ));
        }
        non_negative("contact_erp", self.contact_erp)?;
        non_negative("contact_slop", self.contact_slop)?;
        Ok(())
    }

    /// IK tolerances and the spoon's shape.
    fn check_spoon(&self) -> Result<(), ConfigError> {
        positive("ik_pos_tol", self.ik_pos_tol)?;
        positive("ik_rot_tol", self.ik_rot_tol)?;
        for (i, &v) in self.spoon_bowl_half.iter().enumerate() {
            positive(&format!("spoon_bowl_half[{i}]"), v)?;
        }
        for (i, &v) in self.spoon_rim_height.iter().enumerate() {
            positive(&format!("spoon_rim_height[{i}]"), v)?;
        }
        positive("spoon_rim_thickness", self.spoon_rim_thickness)?;
        positive("spoon_handle_length", self.spoon_handle_length)?;
        if 2.0 * self.food_radius > 2.0 * self.spoon_bowl_half[0] {
            return Err(ConfigError::invalid(
                "food_radius",
                self.food_radius,
                "food wider than the spoon bowl",
            ));
        }
        Ok(())
    }

    /// The person, the furniture and where things start.
    fn check_scene(&self) -> Result<(), ConfigError> {
        non_negative("start_ee_noise", self.start_ee_noise)?;
        non_negative("bowl_noise", self.bowl_noise)?;
        non_negative("head_angle_deg", self.head_angle_deg)?;
        non_negative("tremor_deg", self.tremor_deg)?;
        non_negative("head_motor_gain", self.head_motor_gain)?;
        for (i, &v) in self.head_limit_deg.iter().enumerate() {
            non_negative(&format!("head_limit_deg[{i}]"), v)?;
        }
        if !(self.limits_scale_min > 0.0 && self.limits_scale_min <= 1.0) {
            return Err(ConfigError::invalid(
                "limits_scale_min",
                self.limits_scale_min,
                "must be in (0, 1]",
            ));
        }
        range("base_x_range", self.base_x_range)?;
        range("base_y_range", self.base_y_range)?;
        range("base_yaw_deg_range", self.base_yaw_deg_range)?;
        finite("base_nominal", &self.base_nominal)?;
        finite("start_ee", &self.start_ee)?;
        finite("start_ee_rpy", &self.start_ee_rpy)?;
        finite("bowl", &self.bowl)?;
        finite("table_centre", &self.table_centre)?;
        non_negative("table_height", self.table_height)?;
        for (i, &v) in self.table_size.iter().enumerate() {
            positive(&format!("table_size[{i}]"), v)?;
        }
        Ok(())
    }

    /// The person's profile: weights, threshold and taste.
    fn check_profile(&self) -> Result<(), ConfigError> {
        let w = self.profile.weights.as_array();
        finite("profile.weights", &w)?;
        non_negative(
            "profile.high_force_threshold",
            self.profile.high_force_threshold,
        )?;
        let taste = &self.profile.taste;
        finite("profile.taste.approach", &taste.approach)?;
        finite("profile.taste.approach_weight", &[taste.approach_weight])?;
        finite("profile.taste.bite_weight", &[taste.bite_weight])?;
        non_negative("profile.taste.approach_radius", taste.approach_radius)?;
        non_negative("profile.taste.approach_inner", taste.approach_inner)?;
        let norm = taste.approach.iter().map(|v| v * v).sum::<f32>().sqrt();
        if taste.approach_weight != 0.0 && norm < 1e-6 {
            return Err(ConfigError::invalid(
                "profile.taste.approach",
                format!("{:?}", taste.approach),
                "must not be zero when approach_weight is set: it is a direction",
            ));
        }
        Ok(())
    }
}

fn positive(field: &str, v: f32) -> Result<(), ConfigError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(ConfigError::invalid(
            field,
            v,
            "must be a finite number > 0",
        ))
    }
}
fn non_negative(field: &str, v: f32) -> Result<(), ConfigError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(ConfigError::invalid(
            field,
            v,
            "must be a finite number >= 0",
        ))
    }
}
fn finite(field: &str, vs: &[f32]) -> Result<(), ConfigError> {
    match vs.iter().find(|v| !v.is_finite()) {
        Some(v) => Err(ConfigError::invalid(field, v, "must be finite")),
        None => Ok(()),
    }
}
fn range(field: &str, r: [f32; 2]) -> Result<(), ConfigError> {
    finite(field, &r)?;
    if r[0] <= r[1] {
        Ok(())
    } else {
        Err(ConfigError::invalid(
            field,
            format!("{r:?}"),
            "must be [low, high] with low <= high",
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid() {
        WorldConfig::default().validate().unwrap();
        WorldConfig::fixed().validate().unwrap();
    }

    #[test]
    fn bad_values_name_the_field() {
        let c = WorldConfig {
            food_count: 0,
            ..WorldConfig::default()
        };
        assert_eq!(c.validate().unwrap_err().field, "food_count");
        let c = WorldConfig {
            food_radius: -0.01,
            ..WorldConfig::default()
        };
        let e = c.validate().unwrap_err();
        assert_eq!(e.field, "food_radius");
        assert!(e.to_string().contains("-0.01"), "{e}");
        let mut c = WorldConfig::default();
        c.joint_inertia[3] = f32::NAN;
        assert_eq!(c.validate().unwrap_err().field, "joint_inertia[3]");
        let e = WorldConfig::from_json(r#"{"food_count": 0}"#).unwrap_err();
        assert_eq!(e.field, "food_count");
        let e = WorldConfig::from_json(r#"{"food_radius": -1}"#).unwrap_err();
        assert_eq!(e.field, "food_radius");
        let e = WorldConfig::from_json(r#"{"no_such_field": 1}"#).unwrap_err();
        assert!(e.reason.contains("no_such_field"), "{e}");
        assert_eq!(Profile::by_name("nobody").unwrap_err().field, "profile");
    }
}
