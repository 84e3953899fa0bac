//! A named sequence of values ([`Series`]): a line of a plot, a column of a CSV file. Reports
//! hold them, tables write them, plots draw them.

use serde::{Deserialize, Serialize};

/// A named sequence of values, one per step (or iteration): a line of a plot, a column of a
/// CSV file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct Series {
    /// Its name in legends and headers.
    pub name: String,
    /// The values.
    pub values: Vec<f64>,
    /// Where each value lies on the x axis (a position along the body); `None`: at its
    /// index.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x: Option<Vec<f64>>,
}

impl Series {
    /// A series against its index.
    pub fn new(name: impl Into<String>, values: Vec<f64>) -> Self {
        let (name, x) = (name.into(), None);
        Self { name, values, x }
    }

    /// A series of `values` at `x` (of the same length).
    pub fn at(name: impl Into<String>, x: Vec<f64>, values: Vec<f64>) -> Self {
        debug_assert_eq!(x.len(), values.len());
        let (name, x) = (name.into(), Some(x));
        Self { name, values, x }
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
