//! The shapes of the feeding scene, in one place: the person, the wheelchair, the table and
//! bowl, the spoon and the arm's links. The physics ([`crate::world`]) and the pictures
//! ([`crate::render`]) both build from these.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

use crate::config::WorldConfig;
use crate::kinematics::NJ;

/// A simple convex shape in world (or a parent's) coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// A capsule between two points.
    Capsule {
        a: Point3<f64>,
        b: Point3<f64>,
        radius: f64,
    },
    /// A ball.
    Ball { centre: Point3<f64>, radius: f64 },
    /// An axis-aligned box (in its parent's frame).
    Cuboid {
        centre: Point3<f64>,
        half: Vector3<f64>,
    },
}

impl Shape {
    /// A bounding sphere: (centre, radius).
    pub fn bounding_sphere(&self) -> (Point3<f64>, f64) {
        match *self {
            Shape::Capsule { a, b, radius } => {
                (nalgebra::center(&a, &b), (b - a).norm() / 2.0 + radius)
            }
            Shape::Ball { centre, radius } => (centre, radius),
            Shape::Cuboid { centre, half } => (centre, half.norm()),
        }
    }
}

/// Who a static part belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Owner {
    /// The person: contacts count in C_f, food touching it is a hit.
    Person,
    /// Wheelchair, table, bowl.
    Furniture,
}

/// A named part of the scene that does not move during an episode.
#[derive(Clone, Debug, PartialEq)]
pub struct Part {
    pub name: &'static str,
    pub owner: Owner,
    pub shape: Shape,
}

/// The person's body for one reset: static parts plus the head, which turns.
#[derive(Clone, Debug, PartialEq)]
pub struct Person {
    /// True for the larger body.
    pub large: bool,
    /// The head frame at zero head angles (its origin is the neck pivot of the head).
    pub head_rest: Isometry3<f64>,
    /// The mouth target in the head frame.
    pub mouth_local: Vector3<f64>,
    /// The head ball in the head frame.
    pub head_centre_local: Vector3<f64>,
    /// Head ball radius.
    pub head_radius: f64,
    /// Every part but the head.
    pub parts: Vec<Part>,
}

/// The chair, the person (without the head) and their sizes; `large` picks the body.
pub fn person(large: bool) -> Person {
    let capsule = |name, a: [f64; 3], b: [f64; 3], radius| Part {
        name,
        owner: Owner::Person,
        shape: Shape::Capsule {
            a: Point3::from(a),
            b: Point3::from(b),
            radius,
        },
    };
    // The mouth target at zero head angles and in the head frame (feeding.md); the head
    // frame's origin follows from the two.
    let (mouth_world, mouth_local, head_radius) = if large {
        (
            Vector3::new(0.0, -0.08, 1.2085),
            Vector3::new(0.0, -0.11, 0.03),
            0.08,
        )
    } else {
        (
            Vector3::new(0.0, -0.07, 1.142),
            Vector3::new(0.0, -0.10, 0.03),
            0.075,
        )
    };
    let head_origin = mouth_world - mouth_local;
    // Upper body drops with the chest (0.89 vs 0.86).
    let dz = if large { 0.0 } else { -0.03 };
    let chin = head_origin.z + 0.03 - head_radius;
    let mut parts = vec![
        capsule("torso", [0.0, 0.06, 0.62], [0.0, 0.06, 0.92 + dz], 0.14),
        capsule(
            "neck",
            [0.0, 0.04, 0.98 + dz],
            [0.0, 0.03, chin + 0.02],
            0.05,
        ),
        capsule(
            "left upper arm",
            [0.2, 0.06, 1.0 + dz],
            [0.2, 0.06, 0.76 + dz],
            0.045,
        ),
        capsule(
            "right upper arm",
            [-0.2, 0.06, 1.0 + dz],
            [-0.2, 0.06, 0.76 + dz],
            0.045,
        ),
        capsule(
            "left forearm",
            [0.2, 0.06, 0.76 + dz],
            [0.2, -0.22, 0.76 + dz],
            0.04,
        ),
        capsule(
            "right forearm",
            [-0.2, 0.06, 0.76 + dz],
            [-0.2, -0.22, 0.76 + dz],
            0.04,
        ),
        capsule("left thigh", [0.1, 0.05, 0.52], [0.1, -0.38, 0.52], 0.075),
        capsule(
            "right thigh",
            [-0.1, 0.05, 0.52],
            [-0.1, -0.38, 0.52],
            0.075,
        ),
        capsule("left shin", [0.1, -0.4, 0.5], [0.1, -0.45, 0.12], 0.055),
        capsule("right shin", [-0.1, -0.4, 0.5], [-0.1, -0.45, 0.12], 0.055),
    ];
    let cuboid = |name, c: [f64; 3], h: [f64; 3]| Part {
        name,
        owner: Owner::Furniture,
        shape: Shape::Cuboid {
            centre: Point3::from(c),
            half: Vector3::from(h),
        },
    };
    // The wheelchair stands at (0, 0, 0.06).
    parts.push(cuboid("seat", [0.0, 0.0, 0.42], [0.25, 0.25, 0.03]));
    parts.push(cuboid("backrest", [0.0, 0.26, 0.8], [0.25, 0.03, 0.35]));
    Person {
        large,
        head_rest: Isometry3::from_parts(
            Translation3::from(head_origin),
            UnitQuaternion::identity(),
        ),
        mouth_local,
        head_centre_local: Vector3::new(0.0, 0.0, 0.03),
        head_radius,
        parts,
    }
}

/// The table top and the bowl on it.
pub fn furniture(cfg: &WorldConfig, bowl: [f64; 3]) -> Vec<Part> {
    let th = cfg.table_height as f64;
    let [cx, cy] = cfg.table_centre.map(f64::from);
    let [sx, sy] = cfg.table_size.map(f64::from);
    vec![
        Part {
            name: "table",
            owner: Owner::Furniture,
            shape: Shape::Cuboid {
                centre: Point3::new(cx, cy, th - 0.02),
                half: Vector3::new(sx / 2.0, sy / 2.0, 0.02),
            },
        },
        Part {
            name: "bowl",
            owner: Owner::Furniture,
            shape: Shape::Cuboid {
                centre: Point3::from(bowl),
                half: Vector3::new(0.06, 0.06, 0.025),
            },
        },
    ]
}

/// The spoon's boxes in the spoon frame (origin at the centre of the bowl floor, +y out of
/// the bowl, +z along the handle, the tip at -z).
pub fn spoon_boxes(cfg: &WorldConfig) -> Vec<Shape> {
    let [hx, hz, t] = cfg.spoon_bowl_half.map(f64::from);
    let [h_side, h_back, h_tip] = cfg.spoon_rim_height.map(f64::from);
    let w = cfg.spoon_rim_thickness as f64;
    let len = cfg.spoon_handle_length as f64;
    let b = |c: [f64; 3], h: [f64; 3]| Shape::Cuboid {
        centre: Point3::from(c),
        half: Vector3::from(h),
    };
    vec![
        b([0.0, -t / 2.0, 0.0], [hx + w, t / 2.0, hz + w]),
        b(
            [hx + w / 2.0, h_side / 2.0, 0.0],
            [w / 2.0, h_side / 2.0, hz + w],
        ),
        b(
            [-(hx + w / 2.0), h_side / 2.0, 0.0],
            [w / 2.0, h_side / 2.0, hz + w],
        ),
        b(
            [0.0, h_tip / 2.0, -(hz + w / 2.0)],
            [hx + w, h_tip / 2.0, w / 2.0],
        ),
        b(
            [0.0, h_back / 2.0, hz + w / 2.0],
            [hx + w, h_back / 2.0, w / 2.0],
        ),
        b([0.0, 0.004, hz + w + len / 2.0], [0.006, 0.004, len / 2.0]),
    ]
}

/// Radius of each arm link's capsule, s0 to w2 (the last runs to the gripper).
pub const LINK_RADII: [f64; NJ] = [0.07, 0.07, 0.06, 0.06, 0.05, 0.05, 0.04];

/// Where the food starts, relative to the spoon origin, in world axes: a 2 x 2 grid in
/// two layers for the default 8 particles (feeding.md), more layers for more.
pub fn food_offsets(n: u32) -> Vec<Vector3<f64>> {
    (0..n)
        .map(|k| {
            let (i, j, layer) = (k % 2, (k / 2) % 2, k / 4);
            Vector3::new(
                0.01 * i as f64 - 0.005,
                0.01 * j as f64,
                0.01 * layer as f64 + 0.01,
            )
        })
        .collect()
}
