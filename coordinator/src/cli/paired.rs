//! `coordinator report --repeats`: the runs behind a report's rows, their medians, and the
//! adaptive runs measured against the uniform run each followed (a pair shares the machine's
//! load, so the ratio within a pair is steadier than either time).

use std::fmt::Write;

use tracer_core::convergence::Measurement;

/// One farm render of a report.
pub struct Run {
    pub workers: usize,
    /// The uniform sample count this run is at, or (adaptive) matches in time.
    pub budget: u32,
    pub repeat: u32,
    pub adaptive: bool,
    /// The adaptive job's mean samples per pixel; the budget for a uniform run.
    pub spp_mean: f64,
    pub row: Measurement,
}

fn median(mut values: Vec<f64>) -> Option<f64> {
    values.retain(|v| v.is_finite());
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    let mid = values.len() / 2;
    Some(if values.len() % 2 == 1 {
        values[mid]
    } else {
        (values[mid - 1] + values[mid]) / 2.0
    })
}

/// The row of `runs` (one configuration and budget): each column the median of its runs, so
/// a row's figures may come from different runs. None for no runs.
pub fn median_row(runs: &[&Run]) -> Option<Measurement> {
    let first = runs.first()?;
    let column = |f: &dyn Fn(&Measurement) -> f64| median(runs.iter().map(|r| f(&r.row)).collect());
    let linear = |f: &dyn Fn(&Measurement) -> Option<f64>| {
        let values: Vec<f64> = runs.iter().filter_map(|r| f(&r.row)).collect();
        median(values)
    };
    let spp = median(runs.iter().map(|r| r.spp_mean).collect())?;
    Some(Measurement {
        config: first.row.config.clone(),
        spp: if first.adaptive {
            spp.round() as u32
        } else {
            first.budget
        },
        seconds: column(&|m| m.seconds)?,
        rmse: column(&|m| m.rmse)?,
        rel_mse: column(&|m| m.rel_mse)?,
        mean_flip: column(&|m| m.mean_flip)?,
        rmse_linear: linear(&|m| m.rmse_linear),
        rel_mse_linear: linear(&|m| m.rel_mse_linear),
    })
}

fn optional(value: Option<f64>) -> String {
    value.map_or(String::new(), |v| format!("{v:.6e}"))
}

/// Every run, one line each, errors in full precision.
pub fn runs_csv(runs: &[Run]) -> String {
    let mut out = String::from(
        "workers,budget_spp,repeat,adaptive,spp_mean,seconds,rmse,rel_mse,mean_flip,rmse_linear,rel_mse_linear\n",
    );
    for r in runs {
        let _ = writeln!(
            out,
            "{},{},{},{},{:.3},{:.6},{:.6e},{:.6e},{:.6e},{},{}",
            r.workers,
            r.budget,
            r.repeat,
            r.adaptive,
            r.spp_mean,
            r.row.seconds,
            r.row.rmse,
            r.row.rel_mse,
            r.row.mean_flip,
            optional(r.row.rmse_linear),
            optional(r.row.rel_mse_linear),
        );
    }
    out
}

/// Adaptive over uniform within each pair, as a percentage change (−10 % = adaptive lower).
fn change(adaptive: f64, uniform: f64) -> Option<f64> {
    (uniform > 0.0 && adaptive.is_finite()).then(|| 100.0 * (adaptive / uniform - 1.0))
}

/// The section report.md gains with adaptive runs: per worker count and budget, the median
/// over pairs of the adaptive run's change against the uniform run it followed, and in how
/// many pairs the adaptive image had the lower f32 (else 8-bit) RMSE.
pub fn paired_markdown(runs: &[Run]) -> String {
    let mut out = String::from(
        "\n\n## Adaptive against uniform, pair by pair\n\nEach adaptive run against the uniform \
         run just before it (same budget, time limit = that run's render time): the median \
         over pairs of the change in each figure (negative: the adaptive image is better), and \
         the pairs in which its RMSE (f32 where measured) is lower.\n\n\
         | workers | uniform spp | pairs | adaptive mean spp | seconds | RMSE | relMSE | mean FLIP | RMSE (f32) | relMSE (f32) | adaptive lower |\n\
         |---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    let mut keys: Vec<(usize, u32)> = Vec::new();
    for r in runs.iter().filter(|r| r.adaptive) {
        if !keys.contains(&(r.workers, r.budget)) {
            keys.push((r.workers, r.budget));
        }
    }
    let pct = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:+.1} %"));
    for (workers, budget) in keys {
        let pairs: Vec<(&Run, &Run)> = runs
            .iter()
            .filter(|a| a.adaptive && a.workers == workers && a.budget == budget)
            .filter_map(|a| {
                runs.iter()
                    .find(|u| {
                        !u.adaptive
                            && u.workers == workers
                            && u.budget == budget
                            && u.repeat == a.repeat
                    })
                    .map(|u| (a, u))
            })
            .collect();
        let ratio = |f: &dyn Fn(&Measurement) -> Option<f64>| {
            let changes: Vec<f64> = pairs
                .iter()
                .filter_map(|(a, u)| change(f(&a.row)?, f(&u.row)?))
                .collect();
            median(changes)
        };
        let error = |m: &Measurement| m.rmse_linear.unwrap_or(m.rmse);
        let lower = pairs
            .iter()
            .filter(|(a, u)| error(&a.row) < error(&u.row))
            .count();
        let spp = median(pairs.iter().map(|(a, _)| a.spp_mean).collect());
        let _ = writeln!(
            out,
            "| {workers} | {budget} | {} | {} | {} | {} | {} | {} | {} | {} | {lower} of {} |",
            pairs.len(),
            spp.map_or("–".to_string(), |s| format!("{s:.1}")),
            pct(ratio(&|m| Some(m.seconds))),
            pct(ratio(&|m| Some(m.rmse))),
            pct(ratio(&|m| Some(m.rel_mse))),
            pct(ratio(&|m| Some(m.mean_flip))),
            pct(ratio(&|m| m.rmse_linear)),
            pct(ratio(&|m| m.rel_mse_linear)),
            pairs.len(),
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(adaptive: bool, repeat: u32, rmse: f64, seconds: f64) -> Run {
        Run {
            workers: 1,
            budget: 32,
            repeat,
            adaptive,
            spp_mean: if adaptive { 30.0 + repeat as f64 } else { 32.0 },
            row: Measurement {
                config: if adaptive { "a" } else { "u" }.into(),
                spp: 32,
                seconds,
                rmse,
                rel_mse: rmse * rmse,
                mean_flip: 0.1,
                rmse_linear: Some(rmse),
                rel_mse_linear: None,
            },
        }
    }

    #[test]
    fn a_median_row_takes_each_columns_median() {
        let runs = [
            run(true, 0, 3.0, 1.0),
            run(true, 1, 1.0, 5.0),
            run(true, 2, 2.0, 2.0),
        ];
        let refs: Vec<&Run> = runs.iter().collect();
        let row = median_row(&refs).unwrap();
        assert_eq!((row.rmse, row.seconds, row.spp), (2.0, 2.0, 31));
        assert_eq!((row.rmse_linear, row.rel_mse_linear), (Some(2.0), None));
        assert!(median_row(&[]).is_none());
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), Some(2.5));
    }

    #[test]
    fn pairs_compare_runs_of_the_same_repeat() {
        let runs = vec![
            run(false, 0, 2.0, 1.0),
            run(true, 0, 1.0, 1.0),
            run(false, 1, 4.0, 1.0),
            run(true, 1, 5.0, 1.0),
            run(false, 2, 1.0, 1.0),
            run(true, 2, 0.8, 1.1),
        ];
        let md = paired_markdown(&runs);
        // Changes −50 %, +25 %, −20 %: median −20 %; two of three pairs lower.
        let line = md.lines().last().unwrap();
        assert!(
            line.starts_with("| 1 | 32 | 3 | 31.0 | +0.0 % | -20.0 % |"),
            "{line}"
        );
        assert!(line.ends_with("| 2 of 3 |"), "{line}");
        assert!(runs_csv(&runs)
            .lines()
            .nth(2)
            .unwrap()
            .starts_with("1,32,0,true,30.000,"));
    }
}
