//! Watching an episode again: the world is deterministic, so an episode's seed and actions
//! (what a query carries) and the world config replay it exactly. A labelling page draws
//! the replay as [`Scene`]: the side and front views' static outlines and, per step, the
//! arm, spoon, head, mouth and food, and [`Readout`]: what a person would feel or see at
//! each step (distance to the mouth, speed, force on the person, the food's state).

use anyhow::{bail, Context, Result};
use nalgebra::Point3;
use pbrl_common::Trajectory;
use serde::Serialize;

use crate::kinematics::Arm;
use crate::render::{outline, pose, VIEWS};
use crate::rollout::run_episode_with;
use crate::scene::{self, Owner};
use crate::world::{FeedingWorld, FoodCounts, ACT_DIM};
use crate::WorldConfig;

/// Run the episode of `seed` again with `actions` (`steps` rows of the action size, as the
/// policy gave them).
pub fn resimulate(world: &WorldConfig, seed: u64, actions: &[f32]) -> Result<Trajectory> {
    Ok(watch(world, seed, actions)?.0)
}

/// [`resimulate`], and the food's counts so far at every frame (`steps + 1` rows; the
/// first is the state after reset), which the trajectory keeps only as a final outcome.
pub fn watch(
    world: &WorldConfig,
    seed: u64,
    actions: &[f32],
) -> Result<(Trajectory, Vec<FoodCounts>)> {
    if actions.is_empty() || !actions.len().is_multiple_of(ACT_DIM) {
        bail!(
            "actions: {} numbers are not a positive number of rows of {ACT_DIM}",
            actions.len()
        );
    }
    let steps = actions.len() / ACT_DIM;
    let mut w = FeedingWorld::new(world.clone()).context("building the world to replay")?;
    let mut t = 0;
    let mut food = Vec::with_capacity(steps + 1);
    let traj = run_episode_with(&mut w, seed, |w, _| {
        // NOTE: called before each step, so this is the count after the step before.
        food.push(w.food_counts()?);
        let mut a = [0.0; ACT_DIM];
        // NOTE: the episode cannot outlast its actions: it ends where the original did.
        let row = t.min(steps - 1);
        a.copy_from_slice(&actions[row * ACT_DIM..(row + 1) * ACT_DIM]);
        t += 1;
        Ok(a)
    })
    .context("replaying the episode")?;
    if traj.steps() != steps {
        bail!(
            "the replay of seed {seed} took {} steps where the episode took {steps}: another world config?",
            traj.steps()
        );
    }
    food.push(w.food_counts().context("the food's counts at the end")?);
    Ok((traj, food))
}

/// What a person would feel or see at each frame of an episode (`steps + 1` rows; frame 0
/// is the state after reset, frame k the state after step k), computed by the replay:
/// what a labelling page draws as time strips beside an attempt. Never the ground truth or
/// the preference terms' weighted sum: the measurements a person perceives.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Readout {
    /// Distance from the spoon to the mouth (m).
    pub distance: Vec<f32>,
    /// The end effector's speed over the step that led to the frame (m/s; 0 at frame 0).
    pub speed: Vec<f32>,
    /// Normal force of arm and spoon on the person over that step, the largest over its
    /// substeps (N; 0 at frame 0).
    pub force: Vec<f32>,
    /// The food so far: [on the spoon, eaten, spilled, ever touched the person] (a
    /// particle that fell on the person is both spilled and touched it).
    pub food: Vec<[u32; 4]>,
}

/// The readout of `t` (a feeding trajectory with replay data) from its rewards' terms and
/// the food's counts per frame ([`watch`]).
pub fn readout(t: &Trajectory, food: &[FoodCounts]) -> Result<Readout> {
    let Some(rp) = &t.replay else {
        bail!("trajectory of seed {} has no replay data", t.seed);
    };
    let frames = t.steps() + 1;
    if food.len() != frames || rp.spoon.is_empty() || rp.mouth.is_empty() {
        bail!(
            "the replay of seed {} has {} food counts and {} poses for {frames} frames",
            t.seed,
            food.len(),
            rp.spoon.len()
        );
    }
    let (s, m) = (&rp.spoon[0], &rp.mouth[0]);
    let d0 = ((s[0] - m[0]).powi(2) + (s[1] - m[1]).powi(2) + (s[2] - m[2]).powi(2)).sqrt();
    let per_step = |f: fn(&pbrl_common::StepRewards) -> f32| {
        std::iter::once(0.0)
            .chain(t.rewards.iter().map(f))
            .collect::<Vec<f32>>()
    };
    let mut distance = per_step(|r| -r.task);
    distance[0] = d0;
    let n = rp.n_food;
    Ok(Readout {
        distance,
        // NOTE: C_v = -(EE speed) and C_f = -(force on the person), unweighted.
        speed: per_step(|r| r.terms[2].abs()),
        force: per_step(|r| r.terms[3].abs()),
        food: food
            .iter()
            .map(|c| {
                let gone = c.eaten_total + c.spilled_total;
                [
                    n.saturating_sub(gone),
                    c.eaten_total,
                    c.spilled_total,
                    c.hits_total,
                ]
            })
            .collect(),
    })
}

/// One of the scene's views: its title and which world axes go right and up.
#[derive(Clone, Debug, Serialize)]
pub struct SceneView {
    pub name: &'static str,
    pub title: &'static str,
    pub axes: [usize; 2],
}

/// A static outline, projected on a view's plane (metres), closed.
#[derive(Clone, Debug, Serialize)]
pub struct Outline {
    pub owner: &'static str,
    pub points: Vec<[f32; 2]>,
}

/// What moves, per step (`steps + 1` rows each), in world coordinates (metres).
#[derive(Clone, Debug, Default, Serialize)]
pub struct Frames {
    /// Joint origins, then the end effector, then the spoon.
    pub arm: Vec<Vec<[f32; 3]>>,
    pub spoon: Vec<[f32; 3]>,
    /// The head's centre (a ball of `head_radius`).
    pub head: Vec<[f32; 3]>,
    pub mouth: Vec<[f32; 3]>,
    pub food: Vec<Vec<[f32; 3]>>,
}

/// An episode as a labelling page draws it.
#[derive(Clone, Debug, Serialize)]
pub struct Scene {
    pub steps: usize,
    /// The frame where the judged segment starts; the frames before it are its lead-in
    /// (0 for a whole episode).
    pub segment_from: usize,
    pub views: Vec<SceneView>,
    /// Outlines by view name.
    pub shapes: std::collections::BTreeMap<&'static str, Vec<Outline>>,
    pub head_radius: f32,
    pub frames: Frames,
    /// Per frame, what a person would feel or see (empty until [`Scene::readout`] is set).
    pub readout: Readout,
}

impl Scene {
    /// Only the segment of steps `start .. start + len`, with up to `lead_in` steps
    /// before it: frames `start - lead_in ..= start + len` (clamped to the episode).
    pub fn cut(&mut self, start: usize, len: usize, lead_in: usize) {
        let from = start.saturating_sub(lead_in).min(self.steps);
        let to = (start + len).min(self.steps);
        let f = &mut self.frames;
        fn keep<T>(v: &mut Vec<T>, from: usize, to: usize) {
            if from <= to && to < v.len() {
                v.truncate(to + 1);
                v.drain(..from);
            }
        }
        keep(&mut f.arm, from, to);
        keep(&mut f.spoon, from, to);
        keep(&mut f.head, from, to);
        keep(&mut f.mouth, from, to);
        keep(&mut f.food, from, to);
        let r = &mut self.readout;
        keep(&mut r.distance, from, to);
        keep(&mut r.speed, from, to);
        keep(&mut r.force, from, to);
        keep(&mut r.food, from, to);
        self.steps = to - from;
        self.segment_from = start.min(to) - from;
    }
}

fn p3(p: &Point3<f64>) -> [f32; 3] {
    [p.x as f32, p.y as f32, p.z as f32]
}

/// The scene of `t` (a feeding trajectory with replay data).
pub fn scene(t: &Trajectory, world: &WorldConfig) -> Result<Scene> {
    let Some(rp) = &t.replay else {
        bail!("trajectory of seed {} has no replay data", t.seed);
    };
    let person = scene::person(rp.large_body);
    let mut parts: Vec<(Owner, scene::Shape)> = scene::furniture(world, rp.bowl.map(f64::from))
        .into_iter()
        .map(|p| (p.owner, p.shape))
        .collect();
    parts.extend(person.parts.iter().map(|p| (p.owner, p.shape)));
    parts.sort_by_key(|(owner, _)| *owner == Owner::Person);
    let mut shapes = std::collections::BTreeMap::new();
    let mut views = Vec::new();
    for (view, name) in VIEWS.iter().zip(["side", "front"]) {
        views.push(SceneView {
            name,
            title: view.name,
            axes: [view.axes.0, view.axes.1],
        });
        shapes.insert(
            name,
            parts
                .iter()
                .map(|(owner, shape)| Outline {
                    owner: match owner {
                        Owner::Person => "person",
                        Owner::Furniture => "furniture",
                    },
                    points: outline(view, shape)
                        .into_iter()
                        .map(|(u, v)| [u as f32, v as f32])
                        .collect(),
                })
                .collect(),
        );
    }
    let arm = Arm::baxter();
    let base = pose(&rp.base);
    let centre = Point3::from(person.head_centre_local);
    let n = rp.n_food as usize;
    let mut frames = Frames::default();
    for (k, q) in rp.joints.iter().enumerate() {
        let f = arm.frames(&base, &q.map(f64::from));
        let mut pts: Vec<[f32; 3]> = f
            .joints
            .iter()
            .map(|j| p3(&Point3::from(j.translation.vector)))
            .collect();
        pts.push(p3(&Point3::from(f.ee.translation.vector)));
        pts.push(p3(&Point3::from(f.spoon.translation.vector)));
        frames.arm.push(pts);
        frames
            .spoon
            .push([rp.spoon[k][0], rp.spoon[k][1], rp.spoon[k][2]]);
        frames.head.push(p3(&(pose(&rp.head[k]) * centre)));
        frames.mouth.push(rp.mouth[k]);
        frames.food.push(rp.food[k * n..(k + 1) * n].to_vec());
    }
    Ok(Scene {
        steps: t.steps(),
        segment_from: 0,
        views,
        shapes,
        head_radius: person.head_radius as f32,
        frames,
        readout: Readout::default(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::Controller;
    use crate::rollout::run_episode;

    #[test]
    fn a_cut_scene_keeps_the_segment_and_its_lead_in() {
        let cfg = WorldConfig::default();
        let mut world = FeedingWorld::new(cfg.clone()).unwrap();
        let mut c = Controller::new(crate::controller::ControllerKind::Random);
        let t = run_episode(&mut world, &mut c, 3).unwrap();
        let whole = scene(&t, &cfg).unwrap();
        for (start, len, lead, from, segment_from) in [
            (100, 50, 10, 90, 10),
            (4, 50, 10, 0, 4),
            (180, 50, 10, 170, 10),
        ] {
            let mut s = whole.clone();
            s.cut(start, len, lead);
            let to = (start + len).min(t.steps());
            assert_eq!(s.steps, to - from, "{start}");
            assert_eq!(s.segment_from, segment_from, "{start}");
            assert_eq!(s.frames.spoon.len(), to - from + 1);
            assert_eq!(s.frames.spoon[..], whole.frames.spoon[from..=to]);
            assert_eq!(s.frames.food[..], whole.frames.food[from..=to]);
        }
    }

    #[test]
    fn an_episode_replays_exactly_from_its_seed_and_actions() {
        let cfg = WorldConfig::default();
        let mut world = FeedingWorld::new(cfg.clone()).unwrap();
        let mut c = Controller::new(crate::controller::ControllerKind::Random);
        let original = run_episode(&mut world, &mut c, 11).unwrap();
        let again = resimulate(&cfg, 11, &original.actions).unwrap();
        assert_eq!(again.rewards, original.rewards);
        assert_eq!(again.replay, original.replay);
        let s = scene(&again, &cfg).unwrap();
        assert_eq!(s.frames.arm.len(), original.steps() + 1);
        assert_eq!(s.frames.arm[0].len(), 9);
        assert_eq!(s.frames.food[0].len(), cfg.food_count as usize);
        assert!(!s.shapes["side"].is_empty() && !s.shapes["front"].is_empty());
        // Another seed's actions do not pass for this episode's.
        let other = resimulate(&cfg, 12, &original.actions).unwrap();
        assert_ne!(other.rewards, original.rewards);
    }

    #[test]
    fn the_readout_is_what_the_episode_did_frame_by_frame() {
        let cfg = WorldConfig::default();
        let mut world = FeedingWorld::new(cfg.clone()).unwrap();
        let mut c = Controller::new(crate::controller::ControllerKind::Scripted);
        let original = run_episode(&mut world, &mut c, 5).unwrap();
        let (t, food) = watch(&cfg, 5, &original.actions).unwrap();
        let r = readout(&t, &food).unwrap();
        let frames = t.steps() + 1;
        for (name, len) in [
            ("distance", r.distance.len()),
            ("speed", r.speed.len()),
            ("force", r.force.len()),
            ("food", r.food.len()),
        ] {
            assert_eq!(len, frames, "{name}");
        }
        // The distance is the spoon's to the mouth at every frame, the reset's included.
        let rp = t.replay.as_ref().unwrap();
        for k in 0..frames {
            let (s, m) = (rp.spoon[k], rp.mouth[k]);
            let d = ((s[0] - m[0]).powi(2) + (s[1] - m[1]).powi(2) + (s[2] - m[2]).powi(2)).sqrt();
            assert!(
                (r.distance[k] - d).abs() < 1e-4,
                "frame {k}: {} against {d}",
                r.distance[k]
            );
        }
        assert_eq!((r.speed[0], r.force[0]), (0.0, 0.0));
        assert!(r.speed.iter().all(|v| v.is_finite() && *v >= 0.0));
        assert!(r.speed.iter().any(|v| *v > 0.0), "the arm never moved");
        // The food starts on the spoon; the counts only grow and end at the outcome's.
        let n = cfg.food_count;
        assert_eq!(r.food[0], [n, 0, 0, 0]);
        for w in r.food.windows(2) {
            assert!((1..4).all(|i| w[1][i] >= w[0][i]), "{w:?}");
            assert_eq!(w[1][0] + w[1][1] + w[1][2], n, "{w:?}");
        }
        let o = &t.outcome;
        assert_eq!(r.food[frames - 1][1..], [o.eaten, o.spilled, o.hits]);
        assert!(
            o.eaten > 0,
            "the scripted controller fed nothing: the test shows nothing"
        );
        // Each step's eaten food is the step's C_e.
        for (k, step) in t.rewards.iter().enumerate() {
            assert_eq!(
                (r.food[k + 1][1] - r.food[k][1]) as f32,
                step.terms[1],
                "step {k}"
            );
        }
        // A cut scene keeps the readout's frames with the others'.
        let mut s = scene(&t, &cfg).unwrap();
        s.readout = r.clone();
        s.cut(100, 50, 10);
        assert_eq!(s.readout.distance[..], r.distance[90..=150]);
        assert_eq!(s.readout.food[..], r.food[90..=150]);
    }
}
