//! How reliable the labels of a run are (`pbrl labels stats RUN`): per labeller, the
//! answers by kind and their pace; how often a person answers a query asked again the same
//! way (consistency), how often two people agree on the same query, and how often a person
//! agrees with the oracle that judged the same query on the ground truth (`--shadow
//! oracle`): an online measure of human error.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use rusqlite::{Connection, OpenFlags};

/// Agreements out of comparisons.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Agreement {
    pub agree: u64,
    pub of: u64,
}

impl Agreement {
    fn add(&mut self, same: bool) {
        self.of += 1;
        self.agree += same as u64;
    }

    /// The share that agree, if any were compared.
    pub fn share(&self) -> Option<f64> {
        (self.of > 0).then(|| self.agree as f64 / self.of as f64)
    }
}

/// One labeller (a person's name, or a scripted teacher's id).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LabellerStats {
    pub name: String,
    /// Answers by kind: first, second, equal, skip.
    pub by_kind: BTreeMap<String, u64>,
    pub answers: u64,
    /// Answers to queries asked again (not in D).
    pub repeats: u64,
    /// Time spent answering (the sum of the times to answer), seconds.
    pub answering_s: f64,
    /// Median time to answer, seconds.
    pub median_s: f64,
    /// The same query asked again of this labeller.
    pub consistency: Agreement,
    /// This labeller's first/second answers against the oracle's on the same query.
    pub oracle: Agreement,
}

impl LabellerStats {
    /// Answers (repeats included) per minute spent answering.
    pub fn per_minute(&self) -> Option<f64> {
        (self.answering_s > 0.0)
            .then(|| (self.answers + self.repeats) as f64 * 60.0 / self.answering_s)
    }
}

/// A run's label statistics.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LabelStats {
    pub labellers: Vec<LabellerStats>,
    /// Two labellers' answers to the same query, by pair of names.
    pub between: BTreeMap<(String, String), Agreement>,
    /// Labels of D by the length of the segments they compare (steps; a whole
    /// trajectory's length for the queries of a store before segments).
    pub segment_steps: BTreeMap<u64, u64>,
    /// Labels whose two segments differ in whether food was eaten (one side's segment
    /// eats, the other's does not), and in how many the eating side was preferred: how
    /// much the labels say about feeding itself (None: the store keeps no comfort
    /// features).
    pub food: Option<Agreement>,
}

/// [`LabelStats::food`] of the store at `path`.
fn food_contrast(path: &Path) -> Result<Option<Agreement>> {
    use crate::pref::labels::{LabelStore, StoredSteps};
    use pbrl_common::trajectory::FEATURES;
    use pbrl_common::wire::Preference;
    // NOTE: a store of schema 1 or 2 (read only, not upgraded) keeps no features.
    let Ok(store) = LabelStore::open_read_only(path) else {
        return Ok(None);
    };
    let mut cache: BTreeMap<u64, StoredSteps> = BTreeMap::new();
    let mut eaten = |id: u64, (start, len): (usize, usize)| -> Result<Option<f32>> {
        if let std::collections::btree_map::Entry::Vacant(e) = cache.entry(id) {
            e.insert(store.steps(id)?);
        }
        let s = &cache[&id];
        if s.features.len() != s.steps * FEATURES || start + len > s.steps {
            return Ok(None);
        }
        Ok(Some(
            (start..start + len).map(|k| s.features[k * FEATURES]).sum(),
        ))
    };
    let mut food: Option<Agreement> = None;
    for row in store.labels_since(0)? {
        let (Some(a), Some(b)) = (
            eaten(row.first, row.first_segment)?,
            eaten(row.second, row.second_segment)?,
        ) else {
            continue;
        };
        let f = food.get_or_insert_with(Agreement::default);
        if (a > 0.0) != (b > 0.0) {
            let eating = if a > 0.0 {
                Preference::First
            } else {
                Preference::Second
            };
            f.add(row.preference == eating);
        }
    }
    Ok(food)
}

/// Read the statistics of the label store at `path` (read-only: safe while the run goes).
pub fn stats(path: &Path) -> Result<LabelStats> {
    let db = Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY)
        .with_context(|| format!("opening label store {}", path.display()))?;
    let context = || format!("reading label store {}", path.display());
    let answers: Vec<(String, String, i64, Option<String>)> = db
        .prepare(
            "SELECT coalesce(labeller, teacher_id), answer, coalesce(took_ms, 0), shadow
             FROM queries WHERE answer IN ('first', 'second', 'equal', 'skip')",
        )
        .and_then(|mut s| {
            s.query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))?
                .collect()
        })
        .with_context(context)?;
    let repeats: Vec<(String, String, i64, String, String)> = db
        .prepare(
            "SELECT r.labeller, r.answer, r.took_ms, q.answer, coalesce(q.labeller, q.teacher_id)
             FROM repeats r JOIN queries q ON q.id = r.query
             WHERE q.answer IN ('first', 'second', 'equal', 'skip')",
        )
        .and_then(|mut s| {
            s.query_map([], |r| {
                Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?, r.get(4)?))
            })?
            .collect()
        })
        .with_context(context)?;
    let segment_steps: BTreeMap<u64, u64> = db
        .prepare("SELECT first_len, count(*) FROM labels GROUP BY first_len")
        .and_then(|mut s| {
            s.query_map([], |r| {
                Ok((r.get::<_, i64>(0)? as u64, r.get::<_, i64>(1)? as u64))
            })?
            .collect()
        })
        .with_context(context)?;
    let mut by_name: BTreeMap<String, (LabellerStats, Vec<f64>)> = BTreeMap::new();
    fn entry<'a>(
        by_name: &'a mut BTreeMap<String, (LabellerStats, Vec<f64>)>,
        name: &str,
    ) -> &'a mut (LabellerStats, Vec<f64>) {
        by_name.entry(name.to_string()).or_insert_with(|| {
            (
                LabellerStats {
                    name: name.to_string(),
                    ..LabellerStats::default()
                },
                Vec::new(),
            )
        })
    }
    for (name, answer, took_ms, shadow) in &answers {
        let (s, times) = entry(&mut by_name, name);
        *s.by_kind.entry(answer.clone()).or_default() += 1;
        s.answers += 1;
        times.push(*took_ms as f64 / 1000.0);
        if let Some(oracle) = shadow {
            // NOTE: the oracle never says equal or skip; only a person's choices count.
            if answer == "first" || answer == "second" {
                s.oracle.add(answer == oracle);
            }
        }
    }
    let mut between: BTreeMap<(String, String), Agreement> = BTreeMap::new();
    for (who, answer, took_ms, first_answer, first_who) in &repeats {
        let (s, times) = entry(&mut by_name, who);
        s.repeats += 1;
        times.push(*took_ms as f64 / 1000.0);
        if answer == "skip" || first_answer == "skip" {
            continue;
        }
        if who == first_who {
            s.consistency.add(answer == first_answer);
        } else {
            let key = if first_who < who {
                (first_who.clone(), who.clone())
            } else {
                (who.clone(), first_who.clone())
            };
            between.entry(key).or_default().add(answer == first_answer);
        }
    }
    let labellers = by_name
        .into_values()
        .map(|(mut s, mut times)| {
            s.answering_s = times.iter().sum();
            times.sort_by(f64::total_cmp);
            s.median_s = times.get(times.len() / 2).copied().unwrap_or(f64::NAN);
            s
        })
        .collect();
    Ok(LabelStats {
        labellers,
        between,
        segment_steps,
        food: food_contrast(path)?,
    })
}

/// The statistics as a person reads them.
pub fn report(s: &LabelStats) -> String {
    let pct = |a: &Agreement| match a.share() {
        Some(x) => format!("{:.0}% of {}", 100.0 * x, a.of),
        None => "-".into(),
    };
    let mut out = String::from(
        "labeller              answers  first second equal  skip  per min  median s  consistency    agrees with oracle\n",
    );
    for l in &s.labellers {
        let k = |name: &str| l.by_kind.get(name).copied().unwrap_or(0);
        out += &format!(
            "{:<20} {:>8} {:>6} {:>6} {:>5} {:>5} {:>8} {:>9} {:>12} {:>21}\n",
            l.name,
            l.answers,
            k("first"),
            k("second"),
            k("equal"),
            k("skip"),
            l.per_minute().map_or("-".into(), |x| format!("{x:.1}")),
            if l.median_s.is_nan() {
                "-".into()
            } else {
                format!("{:.1}", l.median_s)
            },
            pct(&l.consistency),
            pct(&l.oracle),
        );
    }
    if !s.segment_steps.is_empty() {
        let parts: Vec<String> = s
            .segment_steps
            .iter()
            .map(|(steps, n)| format!("{n} of {steps} steps"))
            .collect();
        out += &format!("\nlabels by segment length: {}\n", parts.join(", "));
    }
    if let Some(f) = &s.food {
        out += &format!(
            "labels whose segments differ in food eaten (one side eats, the other not): {}, the eating side preferred in {}\n",
            f.of,
            f.share()
                .map_or("-".into(), |x| format!("{:.0}%", 100.0 * x))
        );
    }
    if !s.between.is_empty() {
        out += "\nagreement between labellers (the same query):\n";
        for ((a, b), agreement) in &s.between {
            out += &format!("  {a} and {b}: {}\n", pct(agreement));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pref::labels::{LabelStore, StoredTrajectory};
    use pbrl_common::wire::{Answer, Preference};

    fn person(q: u64, p: Preference, who: &str, shadow: Preference, repeat: bool) -> Answer {
        Answer {
            labeller: who.into(),
            replays: [1, 1],
            shadow: Some(shadow),
            repeat,
            ..Answer::scripted(q, p, "human", "human-0", 3_000)
        }
    }

    #[test]
    fn consistency_agreement_and_the_oracle_are_counted_per_labeller() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("labels.sqlite");
        let mut store = LabelStore::open(&path, "run").unwrap();
        let (obs, actions) = (vec![0.0f32; 4], vec![0.0f32; 2]);
        // Even trajectories eat in their first step, odd ones never.
        let (eats, fasts) = ([[1.0f32; 6], [0.0; 6]].concat(), vec![0.0f32; 12]);
        let traj = |seq: u64| StoredTrajectory {
            actor: 0,
            incarnation: 1,
            seq,
            seed: seq,
            policy_version: 1,
            obs_dim: 2,
            act_dim: 1,
            obs: &obs,
            actions: &actions,
            features: if seq.is_multiple_of(2) { &eats } else { &fasts },
            segment: (0, 2),
        };
        let mut ids = Vec::new();
        for k in 0..4 {
            let asked = store
                .ask(
                    1,
                    "uniform",
                    0,
                    0,
                    // NOTE: the last query compares one-step segments.
                    &StoredTrajectory {
                        segment: if k == 3 { (1, 1) } else { (0, 2) },
                        ..traj(2 * k)
                    },
                    &StoredTrajectory {
                        segment: if k == 3 { (0, 1) } else { (0, 2) },
                        ..traj(2 * k + 1)
                    },
                    |_, _, _| vec![1],
                )
                .unwrap();
            ids.push(asked.query);
        }
        use Preference::{Equal, First, Second};
        // ann: 3 answers, two agree with the oracle of the two it chose a side on.
        store
            .answer(&person(ids[0], First, "ann", First, false), 1)
            .unwrap();
        store
            .answer(&person(ids[1], Second, "ann", First, false), 2)
            .unwrap();
        store
            .answer(&person(ids[2], Equal, "ann", Second, false), 3)
            .unwrap();
        store
            .answer(&person(ids[3], First, "bob", First, false), 4)
            .unwrap();
        // ann again on her first (same) and second (changed); bob on ann's first (agrees),
        // ann on bob's (disagrees).
        store
            .repeat(&person(ids[0], First, "ann", First, true), 5)
            .unwrap();
        store
            .repeat(&person(ids[1], First, "ann", First, true), 6)
            .unwrap();
        store
            .repeat(&person(ids[0], First, "bob", First, true), 7)
            .unwrap();
        store
            .repeat(&person(ids[3], Second, "ann", First, true), 8)
            .unwrap();
        let s = stats(&path).unwrap();
        let ann = s.labellers.iter().find(|l| l.name == "ann").unwrap();
        assert_eq!(ann.answers, 3);
        assert_eq!(ann.consistency, Agreement { agree: 1, of: 2 });
        assert_eq!(ann.oracle, Agreement { agree: 1, of: 2 });
        assert_eq!(
            s.between[&("ann".to_string(), "bob".to_string())],
            Agreement { agree: 1, of: 2 }
        );
        // 3 s per answer: 20 answers a minute.
        assert!((ann.per_minute().unwrap() - 20.0).abs() < 1e-9);
        let text = report(&s);
        assert!(text.contains("ann") && text.contains("50% of 2"), "{text}");
        // Four labels: three of whole 2-step trajectories, one of 1-step segments.
        assert_eq!(s.segment_steps, [(1, 1), (2, 3)].into());
        assert!(text.contains("1 of 1 steps, 3 of 2 steps"), "{text}");
        // The first three compare a segment that eats with one that does not (the last
        // compares steps that eat on neither side): ann preferred the eating side once.
        assert_eq!(s.food, Some(Agreement { agree: 1, of: 3 }));
        assert!(
            text.contains("differ in food eaten (one side eats, the other not): 3, the eating side preferred in 33%"),
            "{text}"
        );
    }
}
