//! Watching an episode again: the world is deterministic, so an episode's seed and actions
//! (what a query carries) and the world config replay it exactly. A labelling page draws
//! the replay as [`Scene`]: the side and front views' static outlines and, per step, the
//! arm, spoon, head, mouth and food.

use anyhow::{bail, Context, Result};
use nalgebra::Point3;
use pbrl_common::Trajectory;
use serde::Serialize;

use crate::kinematics::Arm;
use crate::render::{outline, pose, VIEWS};
use crate::rollout::run_episode_with;
use crate::scene::{self, Owner};
use crate::world::{FeedingWorld, ACT_DIM};
use crate::WorldConfig;

/// Run the episode of `seed` again with `actions` (`steps` rows of the action size, as the
/// policy gave them).
pub fn resimulate(world: &WorldConfig, seed: u64, actions: &[f32]) -> Result<Trajectory> {
    if actions.is_empty() || !actions.len().is_multiple_of(ACT_DIM) {
        bail!(
            "actions: {} numbers are not a positive number of rows of {ACT_DIM}",
            actions.len()
        );
    }
    let steps = actions.len() / ACT_DIM;
    let mut w = FeedingWorld::new(world.clone()).context("building the world to replay")?;
    let mut t = 0;
    let traj = run_episode_with(&mut w, seed, |_, _| {
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
    Ok(traj)
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
}
