//! The report's tables as CSV files (`name.csv`, one row per record, full precision), which
//! [`crate::run`] writes beside the datasets when given a results folder.

use std::fmt::Write as _;

use crate::report::{ExperimentReport, TaskReport};
use crate::series::series_csv;

impl ExperimentReport {
    /// Every table of the report as `(file name, CSV text)`.
    pub fn csv_files(&self) -> Vec<(String, String)> {
        let mut files = Vec::new();
        let mut add = |name: &str, text: String| files.push((name.to_owned(), text));
        match &self.task {
            TaskReport::FitMaterial(r) => {
                let mut csv = String::from("iteration,loss,mu,lambda\n");
                for it in r.output_error.iter().flat_map(|f| &f.iterations) {
                    let c = |k: usize| it.coefficients.get(k).copied().unwrap_or(f64::NAN);
                    let _ = writeln!(csv, "{},{:e},{:e},{:e}", it.iteration, it.loss, c(0), c(1));
                }
                add("iterations.csv", csv);
                add("rollout_error.csv", series_csv("step", &r.rollouts));
            }
            TaskReport::SelectModel(r) => {
                let mut csv = String::from("model,mu,lambda,energy_share\n");
                for m in &r.ensemble.members {
                    let _ = writeln!(
                        csv,
                        "{},{:e},{:e},{:e}",
                        m.model, m.mu, m.lambda, m.energy_share
                    );
                }
                add("members.csv", csv);
            }
            TaskReport::SelectSolver(r) => {
                if let Some(t) = &r.tuning {
                    let mut csv =
                        String::from("projection,log10_newton_rel,log10_eta_max,work,error,cost\n");
                    for (projection, x) in &t.samples {
                        let _ = writeln!(
                            csv,
                            "{},{},{},{:e},{:e},{:e}",
                            projection.map_or("scene's".to_owned(), |p| format!("{p:?}")),
                            x.log10_values[0],
                            x.log10_values.get(1).map_or(String::new(), f64::to_string),
                            x.work,
                            x.error,
                            x.cost
                        );
                    }
                    add("tuning.csv", csv);
                }
                let mut csv = String::from(
                    "case,policy,flops,work,solver_seconds,step_seconds,newton,linear,error,fallbacks,failed\n",
                );
                for case in &r.cases {
                    for row in &case.rows {
                        let m = &row.measured;
                        let _ = writeln!(
                            csv,
                            "\"{}\",\"{}\",{:e},{:e},{},{},{},{},{:e},{},{}",
                            case.label,
                            row.contender.name(),
                            m.flops,
                            m.work,
                            m.seconds,
                            m.step_seconds,
                            m.newton,
                            m.linear,
                            m.error,
                            m.fallbacks,
                            m.failed
                        );
                    }
                }
                add("policies.csv", csv);
                for (ci, case) in r.cases.iter().enumerate() {
                    if let Some(learned) = case.learned() {
                        let mut csv = String::from("iteration,solver\n");
                        for (i, c) in learned.measured.choices.iter().enumerate() {
                            let _ = writeln!(csv, "{i},\"{c}\"");
                        }
                        add(&format!("case{ci}_choices.csv"), csv);
                    }
                }
            }
            TaskReport::TuneBackwardEuler(r) => {
                let mut csv = String::from(
                    "model,mean_error,final_error,work,flops,seconds,newton,fallbacks\n",
                );
                for t in &r.rows {
                    let _ = writeln!(
                        csv,
                        "{},{:e},{:e},{:e},{:e},{},{},{}",
                        t.model.name(),
                        t.mean_error(),
                        t.final_error(),
                        t.work,
                        t.flops,
                        t.seconds,
                        t.newton,
                        t.fallbacks
                    );
                }
                add("comparison.csv", csv);
                let mut csv = String::from("log10_eta_max,work,error,cost\n");
                for x in &r.tuning.samples {
                    let _ = writeln!(
                        csv,
                        "{},{:e},{:e},{:e}",
                        x.log10_values[0], x.work, x.error, x.cost
                    );
                }
                add("tuning.csv", csv);
            }
            TaskReport::TuneSolver(r) => {
                let mut csv: Vec<String> = r
                    .parameters
                    .iter()
                    .map(|p| format!("log10_{p:?}"))
                    .collect();
                csv.extend(["work", "error", "cost"].map(String::from));
                let mut text = csv.join(",") + "\n";
                for s in &r.result.samples {
                    for v in &s.log10_values {
                        let _ = write!(text, "{v},");
                    }
                    let _ = writeln!(text, "{:e},{:e},{:e}", s.work, s.error, s.cost);
                }
                add("tuning.csv", text);
            }
            TaskReport::Coarsen(r) => files.extend(r.csv_files()),
        }
        files
    }
}
