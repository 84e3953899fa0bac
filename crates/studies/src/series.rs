//! A named sequence of values ([`Series`]): a line of a plot, a column of a CSV file. Reports
//! hold them, tables write them, plots draw them.

use serde::{Deserialize, Serialize};

/// A named sequence of values, one per step (or iteration): a line of a plot, a column of a
/// CSV file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Series {
    /// Its name in legends and headers.
    pub name: String,
    /// The values.
    pub values: Vec<f64>,
}

impl Series {
    /// A series.
    pub fn new(name: impl Into<String>, values: Vec<f64>) -> Self {
        Self {
            name: name.into(),
            values,
        }
    }
}

/// Series side by side, one row per index.
pub(crate) fn series_csv(first: &str, series: &[Series]) -> String {
    let mut csv = first.to_owned();
    for s in series {
        csv += &format!(",{}", s.name);
    }
    csv.push('\n');
    for n in 0..series.first().map_or(0, |s| s.values.len()) {
        csv += &n.to_string();
        for s in series {
            csv += &format!(",{:e}", s.values[n]);
        }
        csv.push('\n');
    }
    csv
}
