//! Regions of the coarse mesh (slabs along an axis, or the mesh's own tags), the names of a
//! model's term coefficients, and a field as series for plots.

use super::*;

/// Each element's position along the rest shape's longest axis, from 0 to 1 (by its
/// centroid).
pub(super) fn along_axis(mesh: &TetMesh) -> Vec<f64> {
    let p = mesh.rest_positions();
    let (lo, hi) = p
        .iter()
        .fold((p[0], p[0]), |(lo, hi), q| (lo.inf(q), hi.sup(q)));
    let extent = hi - lo;
    let axis = extent.imax();
    let centroid = |t: &[usize; 4]| t.iter().map(|&v| p[v][axis]).sum::<f64>() / 4.0;
    let along = |t: &[usize; 4]| (centroid(t) - lo[axis]) / extent[axis].max(f64::MIN_POSITIVE);
    mesh.tets().iter().map(along).collect()
}

/// Region tags of `tets` coarse elements from an `.npy` of integers.
pub(super) fn read_tags(file: &Path, tets: usize) -> Result<Vec<u32>, LearnError> {
    let bad = |reason: String| {
        LearnError::Scene(deform_integrator::SceneError::Invalid {
            path: file.to_owned(),
            field: "region_tags".into(),
            reason,
        })
    };
    let a = deform_learn::npy::read(file).map_err(|e| bad(e.to_string()))?;
    if a.shape != [tets] {
        return Err(bad(format!(
            "shape {:?}, expected [{tets}] (coarse tets)",
            a.shape
        )));
    }
    let tags = a.indices().map_err(bad)?;
    tags.into_iter()
        .map(|t| u32::try_from(t).map_err(|_| bad(format!("tag {t} is beyond u32"))))
        .collect()
}

/// Labels of `regions` slabs of equal length along the rest shape's longest axis, by each
/// element's centroid.
pub(super) fn slabs(mesh: &TetMesh, regions: u32) -> Vec<u32> {
    let slab = |s: &f64| ((s * regions as f64) as u32).min(regions - 1);
    along_axis(mesh).iter().map(slab).collect()
}

/// The per-element field as series, one per term, each element at its position along the
/// rest shape's longest axis (0 to 1), in that order.
pub(super) fn field_series(mesh: &TetMesh, coefficients: &[f64]) -> Vec<Series> {
    let along = along_axis(mesh);
    let order = by_position(&along);
    let terms = coefficients.len() / along.len().max(1);
    let values = |j: usize| order.iter().map(|&e| coefficients[e * terms + j]).collect();
    let x: Vec<f64> = order.iter().map(|&e| along[e]).collect();
    let names = term_names(terms).into_iter().enumerate();
    names
        .map(|(j, n)| Series::at(n, x.clone(), values(j)))
        .collect()
}

/// The elements in order of their position `along` an axis (ties by index).
fn by_position(along: &[f64]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..along.len()).collect();
    order.sort_by(|&a, &b| along[a].total_cmp(&along[b]).then(a.cmp(&b)));
    order
}

/// Where regions (`labels`, one per element) meet along the longest axis: the midpoint
/// between consecutive elements of different regions, when each region is one run along it
/// (slabs); none otherwise (tags that interleave along the axis mark no line).
pub(super) fn region_bounds(mesh: &TetMesh, labels: &[u32]) -> Vec<f64> {
    let along = along_axis(mesh);
    let order = by_position(&along);
    let mut bounds = Vec::new();
    let mut seen = std::collections::BTreeSet::new();
    for pair in order.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        seen.insert(labels[a]);
        if labels[a] != labels[b] {
            if seen.contains(&labels[b]) {
                return Vec::new();
            }
            bounds.push(0.5 * (along[a] + along[b]));
        }
    }
    bounds
}

/// Names of the term coefficients of a model with `terms` of them: Lame pairs (`mu`,
/// `lambda`, numbered per ensemble member) or `c0, c1, ...`.
pub(super) fn term_names(terms: usize) -> Vec<String> {
    match terms {
        2 => vec!["mu".into(), "lambda".into()],
        t if t % 2 == 0 => (0..t)
            .map(|j| format!("{}_{}", ["mu", "lambda"][j % 2], j / 2))
            .collect(),
        t => (0..t).map(|j| format!("c{j}")).collect(),
    }
}
