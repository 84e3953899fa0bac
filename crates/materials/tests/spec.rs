//! `MaterialSpec` in RON: every model builds, unknown fields are rejected, and invalid
//! values are reported with the name of the field. `Parametric` round-trips.

use deform_materials::{Lame, Material, MaterialError, MaterialSpec, Model, Parametric};

fn build(text: &str) -> Result<Model, MaterialError> {
    let spec: MaterialSpec = ron::from_str(text).unwrap_or_else(|e| panic!("{text}: {e}"));
    spec.build()
}

#[test]
fn every_model_builds_from_ron() {
    for text in [
        "LinearElastic(Young(e: 1e6, nu: 0.4))",
        "CorotatedLinear(moduli: Lame(mu: 1e5, lambda: 2e5))",
        "CorotatedLinear(moduli: Young(e: 1e6, nu: 0.3), lagged_rotation: true)",
        "FixedCorotated(Young(e: 1e6, nu: 0.45))",
        "StVenantKirchhoff(Young(e: 2e5, nu: 0.2))",
        "NeoHookean(Lame(mu: 1.0, lambda: 3.0))",
        "StableNeoHookean(Young(e: 1e6, nu: 0.49))",
        "Ensemble([(weight: 0.5, model: NeoHookean(Young(e: 1e6, nu: 0.4))), (weight: 0.5, model: LinearElastic(Young(e: 1e6, nu: 0.4)))])",
    ] {
        let m = build(text).unwrap_or_else(|e| panic!("{text}: {e}"));
        assert_eq!(m.psi(&nalgebra::Matrix3::identity()), 0.0, "{text}");
    }
}

#[test]
fn young_and_lame_agree() {
    let l = Lame::from_young(1e6, 0.4).unwrap();
    assert!((l.mu - 1e6 / 2.8).abs() < 1e-6);
    assert!((l.lambda - 1e6 * 0.4 / (1.4 * 0.2)).abs() < 1e-6);
    let (e, nu) = l.to_young();
    assert!((e - 1e6).abs() < 1e-6 && (nu - 0.4).abs() < 1e-12);
}

#[test]
fn unknown_fields_are_rejected() {
    assert!(ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 1e6, nu: 0.4, rho: 3))").is_err());
    assert!(
        ron::from_str::<MaterialSpec>(
            "CorotatedLinear(moduli: Young(e: 1e6, nu: 0.4), lagged: true)"
        )
        .is_err()
    );
    assert!(ron::from_str::<MaterialSpec>("Rubber(Young(e: 1e6, nu: 0.4))").is_err());
}

fn field_of(err: MaterialError) -> String {
    match err {
        MaterialError::InvalidParameter { field, .. } => field,
        other => panic!("expected InvalidParameter, got {other}"),
    }
}

#[test]
fn invalid_values_name_their_field() {
    assert_eq!(
        field_of(build("NeoHookean(Young(e: -1, nu: 0.3))").unwrap_err()),
        "E"
    );
    assert_eq!(
        field_of(build("NeoHookean(Young(e: 1e6, nu: 0.5))").unwrap_err()),
        "nu"
    );
    assert_eq!(
        field_of(build("NeoHookean(Young(e: 1e6, nu: -1.0))").unwrap_err()),
        "nu"
    );
    assert_eq!(
        field_of(build("NeoHookean(Young(e: inf, nu: 0.3))").unwrap_err()),
        "E"
    );
    assert_eq!(
        field_of(build("NeoHookean(Young(e: 1e6, nu: NaN))").unwrap_err()),
        "nu"
    );
    assert_eq!(
        field_of(build("NeoHookean(Lame(mu: 0, lambda: 1))").unwrap_err()),
        "mu"
    );
    assert_eq!(
        field_of(build("NeoHookean(Lame(mu: 1, lambda: -1))").unwrap_err()),
        "lambda"
    );
    let e = build(
        "Ensemble([(weight: 1, model: NeoHookean(Young(e: 1e6, nu: 0.3))), (weight: 1, model: StVenantKirchhoff(Young(e: 1e6, nu: 0.7)))])",
    );
    assert_eq!(field_of(e.unwrap_err()), "members[1].nu");
    let e = build("Ensemble([(weight: -0.5, model: NeoHookean(Young(e: 1e6, nu: 0.3)))])");
    assert_eq!(field_of(e.unwrap_err()), "weights[0]");
    assert!(matches!(
        build("Ensemble([])"),
        Err(MaterialError::InvalidEnsemble(_))
    ));
}

#[test]
fn parametric_round_trips_and_validates() {
    let mut m = build("StVenantKirchhoff(Lame(mu: 2, lambda: 5))").unwrap();
    assert_eq!(m.params(), vec![2.0, 5.0]);
    assert_eq!(m.param_names(), vec!["mu", "lambda"]);
    m.set_params(&[3.0, 4.0]).unwrap();
    assert_eq!(m.params(), vec![3.0, 4.0]);
    assert!(m.set_params(&[-3.0, 4.0]).is_err());
    assert_eq!(
        m.params(),
        vec![3.0, 4.0],
        "a rejected update changes nothing"
    );
    let mut e = build("Ensemble([(weight: 0.5, model: NeoHookean(Lame(mu: 1, lambda: 2))), (weight: 0.25, model: FixedCorotated(Lame(mu: 3, lambda: 4)))])").unwrap();
    assert_eq!(e.params(), vec![0.5, 0.25, 1.0, 2.0, 3.0, 4.0]);
    assert_eq!(e.param_names()[3], "members[0].lambda");
    e.set_params(&[1.0, 0.0, 1.0, 2.0, 5.0, 6.0]).unwrap();
    assert_eq!(e.params(), vec![1.0, 0.0, 1.0, 2.0, 5.0, 6.0]);
    assert_eq!(
        field_of(e.set_params(&[1.0, 0.0, 1.0, 2.0, 5.0, -6.0]).unwrap_err()),
        "members[1].lambda"
    );
    assert!(matches!(
        e.set_params(&[1.0]),
        Err(MaterialError::ParameterCount {
            expected: 6,
            found: 1
        })
    ));
    let mut c = vec![0.0; e.num_terms()];
    e.coefficients(&mut c);
    assert_eq!(c, vec![1.0, 2.0, 0.0, 0.0]);
}
