//! One episode as a picture: the scene from the side and from the front, the spoon's path,
//! the mouth and where each food particle ended.

use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector2};
use pbrl_common::{Replay, Trajectory};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};

use crate::config::WorldConfig;
use crate::kinematics::Arm;
use crate::scene::{self, Owner, Shape};

/// Where a sans-serif TrueType font is looked for (`PBRL_FONT` first).
const FONT_PATHS: [&str; 3] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
];

/// Register a TrueType font for plotters (once per process).
pub fn load_font() -> Result<()> {
    static LOADED: std::sync::OnceLock<Result<(), String>> = std::sync::OnceLock::new();
    LOADED
        .get_or_init(|| {
            let env = std::env::var("PBRL_FONT").ok();
            let candidates: Vec<String> =
                env.into_iter().chain(FONT_PATHS.iter().map(|s| s.to_string())).collect();
            for path in &candidates {
                if let Ok(bytes) = std::fs::read(path) {
                    // NOTE: plotters keeps fonts for the life of the process; this runs once.
                    let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                    return register_font("sans-serif", FontStyle::Normal, bytes)
                        .map_err(|_| format!("{path} is not a TrueType font"));
                }
            }
            Err(format!(
                "no font found for the picture's text (tried {}); install fonts-dejavu-core or set PBRL_FONT to a .ttf file",
                candidates.join(", ")
            ))
        })
        .clone()
        .map_err(|e| anyhow!(e))
}

pub(crate) fn pose(p: &[f32; 7]) -> Isometry3<f64> {
    let p = p.map(f64::from);
    Isometry3::from_parts(
        Translation3::new(p[0], p[1], p[2]),
        UnitQuaternion::from_quaternion(Quaternion::new(p[6], p[3], p[4], p[5])),
    )
}

/// A view: which world axes go right and up.
#[derive(Clone, Copy)]
pub(crate) struct View {
    pub(crate) name: &'static str,
    pub(crate) axes: (usize, usize),
    pub(crate) labels: (&'static str, &'static str),
}

impl View {
    pub(crate) fn project(&self, p: &Point3<f64>) -> (f64, f64) {
        (p[self.axes.0], p[self.axes.1])
    }
}

/// The two views of a feeding scene: side and front.
pub(crate) const VIEWS: [View; 2] = [
    View {
        name: "Side view (from the person's right)",
        axes: (1, 2),
        labels: ("y (m), the person faces -y", "z (m)"),
    },
    View {
        name: "Front view (facing the person)",
        axes: (0, 2),
        labels: ("x (m)", "z (m)"),
    },
];

/// The outline of a shape projected on the view's plane.
pub(crate) fn outline(view: &View, shape: &Shape) -> Vec<(f64, f64)> {
    let circle = |c: (f64, f64), r: f64, from: f64, to: f64| -> Vec<(f64, f64)> {
        (0..=16)
            .map(|k| {
                let t = from + (to - from) * k as f64 / 16.0;
                (c.0 + r * t.cos(), c.1 + r * t.sin())
            })
            .collect()
    };
    match *shape {
        Shape::Ball { centre, radius } => {
            circle(view.project(&centre), radius, 0.0, std::f64::consts::TAU)
        }
        Shape::Capsule { a, b, radius } => {
            let (pa, pb) = (view.project(&a), view.project(&b));
            let d = Vector2::new(pb.0 - pa.0, pb.1 - pa.1);
            if d.norm() < 1e-9 {
                return circle(pa, radius, 0.0, std::f64::consts::TAU);
            }
            let ang = d.y.atan2(d.x);
            let h = std::f64::consts::FRAC_PI_2;
            let mut pts = circle(pb, radius, ang - h, ang + h);
            pts.extend(circle(pa, radius, ang + h, ang + 3.0 * h));
            pts
        }
        Shape::Cuboid { centre, half } => {
            let (c, (hx, hy)) = (
                view.project(&centre),
                (half[view.axes.0], half[view.axes.1]),
            );
            vec![
                (c.0 - hx, c.1 - hy),
                (c.0 + hx, c.1 - hy),
                (c.0 + hx, c.1 + hy),
                (c.0 - hx, c.1 + hy),
            ]
        }
    }
}

fn draw_err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("drawing the picture: {e:?}")
}

/// What a picture of an episode shows, in the world frame.
struct Picture {
    /// Furniture first, the person over it, the head last, so nothing hides the face.
    shapes: Vec<(Owner, Shape)>,
    arm_start: Vec<Point3<f64>>,
    arm_end: Vec<Point3<f64>>,
    spoon_path: Vec<Point3<f64>>,
    mouth: Point3<f64>,
    /// Each particle where it ended, and what became of it.
    food_end: Vec<Point3<f64>>,
    food_outcome: Vec<u8>,
}

impl Picture {
    fn of(rp: &Replay, cfg: &WorldConfig) -> Self {
        let person = scene::person(rp.large_body);
        let bowl = rp.bowl.map(f64::from);
        let mut shapes: Vec<(Owner, Shape)> = scene::furniture(cfg, bowl)
            .into_iter()
            .map(|p| (p.owner, p.shape))
            .collect();
        shapes.extend(person.parts.iter().map(|p| (p.owner, p.shape)));
        // NOTE: furniture first, the person over it, the head last, so nothing hides the face.
        shapes.sort_by_key(|(owner, _)| *owner == Owner::Person);
        let head = pose(&rp.head[0]);
        shapes.push((
            Owner::Person,
            Shape::Ball {
                centre: head * Point3::from(person.head_centre_local),
                radius: person.head_radius,
            },
        ));
        let arm = Arm::baxter();
        let base = pose(&rp.base);
        let arm_points = |q: &[f32; 7]| -> Vec<Point3<f64>> {
            let f = arm.frames(&base, &q.map(f64::from));
            let mut pts: Vec<Point3<f64>> = f
                .joints
                .iter()
                .map(|j| Point3::from(j.translation.vector))
                .collect();
            pts.push(Point3::from(f.ee.translation.vector));
            pts.push(Point3::from(f.spoon.translation.vector));
            pts
        };
        let arm_start = arm_points(&rp.joints[0]);
        let arm_end = arm_points(rp.joints.last().expect("checked non-empty above"));
        let spoon_path: Vec<Point3<f64>> = rp
            .spoon
            .iter()
            .map(|p| Point3::new(p[0], p[1], p[2]).cast())
            .collect();
        let mouth = Point3::from(rp.mouth[0].map(f64::from));
        let n = rp.n_food as usize;
        let last = rp.food.len() / n.max(1) - 1;
        let food_end: Vec<Point3<f64>> = (0..n)
            .map(|k| Point3::from(rp.food[last * n + k].map(f64::from)))
            .collect();
        Self {
            shapes,
            arm_start,
            arm_end,
            spoon_path,
            mouth,
            food_end,
            food_outcome: rp.food_outcome.clone(),
        }
    }
}

/// One view of the picture, at equal scale on both axes.
fn draw_view(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    view: &View,
    pic: &Picture,
) -> Result<()> {
    // The region of interest: arm, spoon path, head; equal scale on both axes.
    let mut pts: Vec<(f64, f64)> = pic.spoon_path.iter().map(|p| view.project(p)).collect();
    pts.extend(
        pic.arm_start
            .iter()
            .chain(&pic.arm_end)
            .map(|p| view.project(p)),
    );
    pts.push(view.project(&pic.mouth));
    pts.push(view.project(&Point3::new(0.0, 0.0, 0.4)));
    let (mut x0, mut x1, mut y0, mut y1) = pts.iter().fold(
        (f64::MAX, f64::MIN, f64::MAX, f64::MIN),
        |(a, b, c, d), p| (a.min(p.0), b.max(p.0), c.min(p.1), d.max(p.1)),
    );
    let pad = 0.12;
    (x0, x1, y0, y1) = (x0 - pad, x1 + pad, y0 - pad, y1 + pad);
    let (w, h) = area.dim_in_pixel();
    let (pw, ph) = (w as f64 - 90.0, h as f64 - 90.0);
    let scale = (pw / (x1 - x0)).min(ph / (y1 - y0));
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    let (hw, hh) = (pw / scale / 2.0, ph / scale / 2.0);
    let mut chart = ChartBuilder::on(area)
        .caption(view.name, ("sans-serif", 20))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(cx - hw..cx + hw, cy - hh..cy + hh)
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .x_desc(view.labels.0)
        .y_desc(view.labels.1)
        .light_line_style(RGBColor(240, 240, 240))
        .draw()
        .map_err(draw_err)?;
    for (owner, shape) in &pic.shapes {
        let fill = match owner {
            Owner::Person => RGBColor(246, 214, 190),
            Owner::Furniture => RGBColor(205, 205, 205),
        };
        let pts = outline(view, shape);
        chart
            .draw_series(std::iter::once(Polygon::new(pts.clone(), fill.filled())))
            .map_err(draw_err)?;
        let mut closed = pts;
        closed.push(closed[0]);
        chart
            .draw_series(std::iter::once(PathElement::new(
                closed,
                RGBColor(120, 120, 120),
            )))
            .map_err(draw_err)?;
    }
    for (pts, colour, label) in [
        (&pic.arm_start, RGBColor(170, 170, 170), "arm at the start"),
        (&pic.arm_end, RGBColor(60, 60, 60), "arm at the end"),
    ] {
        chart
            .draw_series(std::iter::once(PathElement::new(
                pts.iter().map(|p| view.project(p)).collect::<Vec<_>>(),
                colour.stroke_width(4),
            )))
            .map_err(draw_err)?
            .label(label)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(4))
            });
    }
    chart
        .draw_series(LineSeries::new(
            pic.spoon_path.iter().map(|p| view.project(p)),
            BLUE.stroke_width(2),
        ))
        .map_err(draw_err)?
        .label("spoon path")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
    chart
        .draw_series(std::iter::once(Circle::new(
            view.project(&pic.mouth),
            7,
            RED.stroke_width(3),
        )))
        .map_err(draw_err)?
        .label("mouth target")
        .legend(|(x, y)| Circle::new((x + 10, y), 6, RED.stroke_width(3)));
    for (state, colour, label) in [
        (0u8, RGBColor(230, 140, 0), "food left on the spoon"),
        (1, RGBColor(0, 150, 60), "food eaten"),
        (2, RGBColor(200, 0, 200), "food spilled"),
    ] {
        let pts: Vec<(f64, f64)> = pic
            .food_end
            .iter()
            .zip(&pic.food_outcome)
            .filter(|(_, s)| **s == state)
            .map(|(p, _)| view.project(p))
            .collect();
        chart
            .draw_series(pts.into_iter().map(|p| Circle::new(p, 4, colour.filled())))
            .map_err(draw_err)?
            .label(label)
            .legend(move |(x, y)| Circle::new((x + 10, y), 4, colour.filled()));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .draw()
        .map_err(draw_err)?;
    Ok(())
}

/// Draw `t` (a feeding trajectory with replay data) to the PNG `out`.
pub fn render(t: &Trajectory, cfg: &WorldConfig, controller: &str, out: &Path) -> Result<()> {
    let Some(rp) = &t.replay else {
        bail!("trajectory of seed {} has no replay data to draw", t.seed);
    };
    if rp.spoon.is_empty() {
        bail!("trajectory of seed {} has no steps to draw", t.seed);
    }
    load_font()?;
    let pic = Picture::of(rp, cfg);
    let root = BitMapBackend::new(out, (1500, 760)).into_drawing_area();
    root.fill(&WHITE).map_err(draw_err)?;
    let (top, body) = root.split_vertically(60);
    let o = &t.outcome;
    top.draw_text(
        &format!(
            "Feeding episode, seed {}, {} controller: eaten {}/{}, spilled {}, food on the person {}, {}; return {:.1} (preference part {:.1})",
            t.seed,
            controller,
            o.eaten,
            o.food,
            o.spilled,
            o.hits,
            if o.success { "success" } else { "no success" },
            o.return_truth,
            o.return_human
        ),
        &("sans-serif", 22).into_font().color(&BLACK),
        (20, 20),
    )
    .map_err(draw_err)?;
    for (area, view) in body.split_evenly((1, 2)).iter().zip(VIEWS) {
        draw_view(area, &view, &pic)?;
    }
    root.present()
        .map_err(draw_err)
        .with_context(|| format!("writing {}", out.display()))?;
    Ok(())
}
