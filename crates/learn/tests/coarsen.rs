//! Coarse-from-fine data: nested beams embed exactly, constraints map onto the coarse
//! vertices that lie on them.

use std::path::Path;

use deform_integrator::Scene;
use deform_integrator::scene::MeshSource;
use deform_learn::coarsen::{Constraints, coarsen};
use deform_learn::dataset::{DatasetSpec, generate};
use deform_mesh::generate::BoxGrid;
use deform_mesh::select::Selector;

const FINE: &str = r#"Scene(name: "fine", mesh: Beam(4), material: NeoHookean(Young(e: 2e5, nu: 0.35)),
    density: 1000.0, constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
    integrator: (dt: 0.01, newton: (rel: 1e-9)), steps: 4)"#;

#[test]
fn nested_beams_carry_the_fine_states_exactly_with_the_fine_constraints() {
    let origin = Path::new("fine.ron");
    let fine = Scene::parse(FINE, origin).unwrap();
    let data = generate(&fine, origin, &DatasetSpec::new(2, 4, 11), |_, _| ()).unwrap();
    let fine_mesh = BoxGrid::beam(4).build().unwrap();
    for n in [2, 1] {
        let coarse = fine
            .clone()
            .mesh(MeshSource::Beam(n))
            .constraints(Vec::new());
        let (mapped, report) = coarsen(&data, &coarse, origin, Constraints::FromFine).unwrap();
        let coarse_mesh = BoxGrid::beam(n).build().unwrap();
        assert_eq!(report.ratio, (4 / n).pow(3) as f64);
        assert_eq!((report.outside, report.max_distance), (0, 0.0));
        // Every coarse vertex is a fine vertex: its states are the fine ones, to rounding.
        let twin: Vec<usize> = coarse_mesh
            .rest_positions()
            .iter()
            .map(|p| {
                let near = |v: &usize| (fine_mesh.rest_positions()[*v] - p).norm();
                (0..fine_mesh.num_vertices())
                    .min_by(|a, b| near(a).total_cmp(&near(b)))
                    .unwrap()
            })
            .collect();
        for (t, f) in mapped.trajectories.iter().zip(&data.trajectories) {
            assert_eq!(t.x.len(), f.x.len());
            for (states, fine_states) in [(&t.x, &f.x), (&t.v, &f.v)] {
                for (s, fs) in states.iter().zip(fine_states) {
                    for (i, &v) in twin.iter().enumerate() {
                        for d in 0..3 {
                            assert!((s[3 * i + d] - fs[3 * v + d]).abs() < 1e-12);
                        }
                    }
                }
            }
        }
        // The clamp at x = 0, mapped, is the coarse beam's own x = 0 face.
        let plane = Selector::Plane {
            point: [0.0; 3],
            normal: [-1.0, 0.0, 0.0],
        };
        let own = plane.select(&coarse_mesh).unwrap();
        let Selector::Indices(mapped_set) = &mapped.meta.scene.constraints[0].select else {
            panic!("mapped constraints are index sets")
        };
        assert_eq!(mapped_set, &own);
        assert_eq!(report.constrained, vec![own.len()]);
        assert_eq!(mapped.meta.vertices, coarse_mesh.num_vertices());
    }
    // Its own selectors, when asked for, are kept.
    let own = fine.clone().mesh(MeshSource::Beam(1));
    let (mapped, _) = coarsen(&data, &own, origin, Constraints::OwnSelectors).unwrap();
    assert_eq!(mapped.meta.scene.constraints, fine.constraints);
}

#[test]
fn a_saved_coarse_model_reloads_and_simulates_bit_identically() {
    use deform_assembly::MaterialField;
    use deform_integrator::{NoObserver, RunOptions};
    let dir = tempfile::tempdir().unwrap();
    let origin = Path::new("fine.ron");
    let fine = Scene::parse(FINE, origin).unwrap();
    // A mesh from a file (copied beside the saved scene) and a generated one (kept).
    let msh = dir.path().join("coarse_input.msh");
    let format = deform_mesh::io::MshFormat::default();
    deform_mesh::io::write_msh(&msh, &BoxGrid::beam(1).build().unwrap(), format).unwrap();
    for (name, mesh) in [
        ("from_file", MeshSource::File(msh.clone())),
        ("generated", MeshSource::Beam(1)),
    ] {
        let scene = fine.clone().name(name.into()).mesh(mesh);
        let mut sim = scene.build(origin).unwrap();
        let model = scene.material.build().unwrap();
        let mut rng = deform_learn::rng::Rng::new(9);
        let tets = sim.mesh.num_tets();
        let base = model.term_coefficients();
        let c: Vec<f64> = (0..tets * base.len())
            .map(|k| base[k % base.len()] * 10f64.powf(rng.range(-0.5, 0.5)))
            .collect();
        let models = c
            .chunks(2)
            .map(|c| model.with_term_coefficients(c).unwrap())
            .collect();
        let field = MaterialField::PerElement {
            models,
            index: (0..tets as u32).collect(),
        };
        sim.integrator.assembly_mut().set_materials(field).unwrap();
        // Learned mass scales too.
        let scale: Vec<f64> = (0..sim.mesh.num_vertices())
            .map(|_| rng.range(0.5, 2.0))
            .collect();
        sim.integrator.set_mass_scale(Some(&scale)).unwrap();
        let saved = dir.path().join("saved");
        let written = deform_learn::coarsen::save_model(&scene, &c, Some(&scale), &saved).unwrap();
        assert!(
            written
                .iter()
                .any(|p| p.ends_with(format!("{name}.mass_scale.npy")))
        );
        let path = written[0].clone();
        let loaded = Scene::load(&path).unwrap();
        let mut back = loaded.build(&path).unwrap();
        let options = RunOptions::steps(5);
        sim.integrator
            .run(&mut sim.state, &options, &mut NoObserver)
            .into_result()
            .unwrap();
        back.integrator
            .run(&mut back.state, &options, &mut NoObserver)
            .into_result()
            .unwrap();
        assert_eq!(sim.state.x, back.state.x, "{name}");
        assert_eq!(sim.state.v, back.state.v, "{name}");
        // A field of the wrong size is refused naming the field.
        let e = deform_learn::coarsen::save_model(&scene, &c[1..], None, dir.path()).unwrap_err();
        assert!(e.to_string().contains("coefficients"), "{e}");
        let e = deform_learn::coarsen::save_model(&scene, &c, Some(&scale[1..]), dir.path())
            .unwrap_err();
        assert!(e.to_string().contains("mass_scale"), "{e}");
    }
}

#[test]
fn a_per_element_fit_finds_a_stiff_inclusion_the_coarse_elements_straddle() {
    use deform_learn::dataset::{Split, Variations};
    let dir = tempfile::tempdir().unwrap();
    let origin = dir.path().join("fine.ron");
    // The fine truth: E 20x higher for 7/16 <= x <= 11/16, an inclusion whose ends cut
    // through coarse cells (1/8 wide).
    let mut fine = Scene::parse(FINE, &origin).unwrap();
    let mesh = BoxGrid::beam(4).build().unwrap();
    let soft = fine.material.build().unwrap();
    let stiff = soft
        .term_coefficients()
        .iter()
        .map(|c| 20.0 * c)
        .collect::<Vec<_>>();
    let inside = |e: usize, mesh: &deform_mesh::TetMesh| {
        let x: f64 = mesh.tets()[e]
            .iter()
            .map(|&v| mesh.rest_positions()[v].x)
            .sum::<f64>()
            / 4.0;
        (7.0 / 16.0..=11.0 / 16.0).contains(&x)
    };
    let field: Vec<f64> = (0..mesh.num_tets())
        .flat_map(|e| {
            if inside(e, &mesh) {
                stiff.clone()
            } else {
                soft.term_coefficients()
            }
        })
        .collect();
    deform_learn::npy::write(&dir.path().join("truth.npy"), &[mesh.num_tets(), 2], &field).unwrap();
    fine.coefficients = Some(dir.path().join("truth.npy"));
    let spec = DatasetSpec::new(3, 20, 5)
        .variations(
            Variations::default()
                .speed(0.3)
                .spin(1.0)
                .stretch(0.0)
                .rest(false),
        )
        .split((0.67, 0.0));
    let data = generate(&fine, &origin, &spec, |_, _| ()).unwrap();
    let coarse = fine.clone().mesh(MeshSource::Beam(2)).coefficients(None);
    let (data, _) = coarsen(&data, &coarse, &origin, Constraints::FromFine).unwrap();
    let mut sim = data.meta.scene.build(&origin).unwrap();
    let tets = sim.mesh.num_tets();
    let labels: Vec<u32> = (0..tets as u32).collect();
    let options = deform_learn::OutputErrorOptions::default()
        .rollout(5)
        .max_iterations(40);
    let train = data.split(Split::Train);
    let field = deform_learn::Field::default().labels(labels);
    let fit = deform_learn::fit_output_error_field(
        &mut sim.integrator,
        &train,
        &field,
        options,
        |_, _| (),
    )
    .unwrap();
    assert!(
        fit.loss < 0.5 * fit.initial_loss,
        "{} -> {}",
        fit.initial_loss,
        fit.loss
    );
    let mean_mu = |pick: &dyn Fn(usize) -> bool| {
        let mus: Vec<f64> = (0..tets)
            .filter(|&e| pick(e))
            .map(|e| fit.coefficients[2 * e])
            .collect();
        mus.iter().sum::<f64>() / mus.len() as f64
    };
    let centroid = |e: usize| {
        sim.mesh.tets()[e]
            .iter()
            .map(|&v| sim.mesh.rest_positions()[v].x)
            .sum::<f64>()
            / 4.0
    };
    let covering = mean_mu(&|e| (0.375..=0.75).contains(&centroid(e)));
    let before = mean_mu(&|e| centroid(e) < 0.375);
    eprintln!(
        "mean mu: covering the inclusion {covering:.4e}, between clamp and inclusion {before:.4e}, truth {:.4e} / {:.4e}",
        soft.term_coefficients()[0],
        stiff[0]
    );
    assert!(
        covering > 2.0 * before,
        "covering {covering:e}, before {before:e}"
    );
}

#[test]
fn gmsh_meshes_of_one_shape_coarsen_with_the_clamp_mapped() {
    let assets = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/meshes");
    let origin = Path::new("fine.ron");
    let mut fine = Scene::parse(FINE, origin).unwrap();
    fine.mesh = MeshSource::File(assets.join("beam_fine.msh"));
    let data = generate(&fine, origin, &DatasetSpec::new(1, 2, 3), |_, _| ()).unwrap();
    let coarse = fine
        .clone()
        .mesh(MeshSource::File(assets.join("beam_coarse.msh")));
    let (mapped, report) = coarsen(&data, &coarse, origin, Constraints::FromFine).unwrap();
    assert!(report.ratio > 12.0, "{}", report.ratio);
    assert!(report.max_distance < 1e-12);
    // Unstructured meshes share no vertices, yet the clamped face maps onto the coarse one.
    let coarse_mesh = coarse.build(origin).unwrap().mesh;
    let plane = Selector::Plane {
        point: [0.0; 3],
        normal: [-1.0, 0.0, 0.0],
    };
    let own = plane.select(&coarse_mesh).unwrap();
    let Selector::Indices(mapped_set) = &mapped.meta.scene.constraints[0].select else {
        panic!("index set")
    };
    assert_eq!(mapped_set, &own);
    // The clamped coarse vertices stay where the fine clamp holds them.
    let last = mapped.trajectories[0].x.last().unwrap();
    for &v in &own {
        let p = coarse_mesh.rest_positions()[v];
        for d in 0..3 {
            assert!((last[3 * v + d] - p[d]).abs() < 1e-12);
        }
    }
}
