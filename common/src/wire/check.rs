//! What a decoded message must hold beyond its layout: shapes that agree, finite numbers,
//! names within bounds. Each refusal names the field and the value.

use super::{
    check_labeller, check_teacher_id, Answer, Body, EvalResult, EvalSteps, Preference, Query,
    WireError, MAX_ATTEMPTS,
};

/// Check a decoded message's body.
pub(super) fn body(body: &Body) -> Result<(), WireError> {
    match body {
        Body::Weights(w) => w.validate()?,
        Body::Trajectory(t) => t.trajectory.validate()?,
        Body::EvalRequest(r) => r.weights.validate()?,
        Body::EvalResult(r) => eval_result(r)?,
        Body::Stop(_) => {}
        Body::Query(q) => query(q)?,
        Body::Answer(a) => {
            check_teacher_id("teacher_id", &a.teacher_id)?;
            if a.teacher.is_empty() || a.teacher.len() > 64 {
                return Err(WireError::Invalid {
                    field: "teacher".into(),
                    value: a.teacher.chars().take(80).collect(),
                    reason: "must be 1 to 64 characters long",
                });
            }
            check_labeller("labeller", &a.labeller)?;
            ranks(a)?;
        }
        Body::AnswerAck(a) => {
            check_teacher_id("teacher_id", &a.teacher_id)?;
            for (_, l) in &a.repeats {
                check_labeller("repeats.labeller", l)?;
            }
        }
        Body::Status(_) => {}
    }
    Ok(())
}

/// A ranking's places: one per attempt (3 or 4), each a place among them, and the
/// preference the order of the first two.
fn ranks(a: &Answer) -> Result<(), WireError> {
    if a.ranks.is_empty() {
        return Ok(());
    }
    let n = a.ranks.len();
    let bad = |reason| WireError::Invalid {
        field: "ranks".into(),
        value: format!("{:?}", a.ranks),
        reason,
    };
    if !(3..=MAX_ATTEMPTS).contains(&n) {
        return Err(bad(
            "a ranking places 3 or 4 attempts (a pair's answer has none)",
        ));
    }
    if a.ranks.iter().any(|&r| r as usize >= n) {
        return Err(bad("each place must be below the number of attempts"));
    }
    if a.preference != Preference::of_places(a.ranks[0], a.ranks[1]) {
        return Err(bad(
            "the preference must be the order of the first two attempts",
        ));
    }
    Ok(())
}

/// An evaluation's returns are finite and its steps, where sent, are one per episode.
fn eval_result(r: &EvalResult) -> Result<(), WireError> {
    for (k, o) in r.episodes.iter().chain(&r.sampled).enumerate() {
        let sums = [
            o.return_truth,
            o.return_human,
            o.return_robot,
            o.return_task,
        ];
        if sums.iter().any(|x| !x.is_finite()) {
            return Err(WireError::NonFinite {
                field: format!("episodes[{k}] returns"),
            });
        }
    }
    if !r.steps.is_empty() && r.steps.len() != r.episodes.len() {
        return Err(WireError::Shape {
            field: "steps".into(),
            found: r.steps.len(),
            expected: r.episodes.len(),
        });
    }
    for (k, e) in r.steps.iter().enumerate() {
        eval_steps(k, e)?;
    }
    Ok(())
}

/// Episode `k`'s steps: every array the same number of steps, every number finite.
fn eval_steps(k: usize, e: &EvalSteps) -> Result<(), WireError> {
    let n = e.truth.len().max(1);
    for (name, xs) in [("obs", &e.obs), ("actions", &e.actions)] {
        if xs.len() % n != 0 || xs.is_empty() != e.truth.is_empty() {
            return Err(WireError::Shape {
                field: format!("steps[{k}].{name}"),
                found: xs.len(),
                expected: xs.len().div_ceil(n) * e.truth.len(),
            });
        }
    }
    let features = e.truth.len() * crate::trajectory::FEATURES;
    if !e.features.is_empty() && e.features.len() != features {
        return Err(WireError::Shape {
            field: format!("steps[{k}].features"),
            found: e.features.len(),
            expected: features,
        });
    }
    for (name, xs) in [("human", &e.human), ("task", &e.task)] {
        if xs.len() != e.truth.len() {
            return Err(WireError::Shape {
                field: format!("steps[{k}].{name}"),
                found: xs.len(),
                expected: e.truth.len(),
            });
        }
    }
    if e.obs
        .iter()
        .chain(&e.actions)
        .chain(&e.truth)
        .chain(&e.human)
        .chain(&e.task)
        .chain(&e.features)
        .any(|x| !x.is_finite())
    {
        return Err(WireError::NonFinite {
            field: format!("steps[{k}]"),
        });
    }
    Ok(())
}

/// Every attempt's actions as long as its steps, finite, and a segment within each; at
/// most [`MAX_ATTEMPTS`] attempts.
fn query(q: &Query) -> Result<(), WireError> {
    if q.len() > MAX_ATTEMPTS {
        return Err(WireError::Invalid {
            field: "more".into(),
            value: format!("{} attempts", q.len()),
            reason: "a query shows at most 4 attempts",
        });
    }
    let names = ["first", "second", "more[0]", "more[1]"];
    for (side, s) in names.iter().zip(q.attempts()) {
        if s.actions.len() != s.steps() * s.act_dim as usize {
            return Err(WireError::Shape {
                field: format!("{side}.actions"),
                found: s.actions.len(),
                expected: s.steps() * s.act_dim as usize,
            });
        }
        if s.truth.iter().chain(&s.actions).any(|x| !x.is_finite()) {
            return Err(WireError::NonFinite {
                field: format!("{side}.truth or {side}.actions"),
            });
        }
        if s.len == 0 || s.start as u64 + s.len as u64 > s.steps() as u64 {
            return Err(WireError::Invalid {
                field: format!("{side}.start, {side}.len"),
                value: format!("{}, {} of {} steps", s.start, s.len, s.steps()),
                reason: "the segment must hold at least one step of the trajectory",
            });
        }
    }
    if q.r_avg.is_some_and(|r| !r.is_finite()) {
        return Err(WireError::NonFinite {
            field: "r_avg".into(),
        });
    }
    Ok(())
}
