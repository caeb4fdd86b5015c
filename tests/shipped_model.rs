//! The shipped model (`models/tiny-synthetic`, compiled into the binary) on the demo's
//! held-out subjects: the demo's own pipeline at `--quick` scale (seed 0, as `demo
//! --quick` runs it; one training epoch for the model the demo trains, which does not
//! change the data), and the shipped model's scores against the mean pose's.

use arkit_tool::demo::{self, DemoPlan, DemoProgress};

struct Quiet;

impl DemoProgress for Quiet {
    fn stage(&self, _: usize, _: &str) {}
    fn advance(&self, _: u64) {}
}

#[test]
fn shipped_model_beats_the_mean_pose_3x_on_the_demos_held_out_subjects() {
    let plan = DemoPlan {
        epochs: 1,
        ..DemoPlan::quick(0)
    };
    // The shipped model takes what the demo renders.
    let c = arkit_perspnet::shipped_checkpoint().unwrap();
    assert_eq!(c.config.input_size, plan.crop as usize);
    assert_eq!(c.config.points, plan.points);
    let topology = arkit_data::mesh::builtin().topology.clone();
    assert_eq!(c.topology, topology.source);

    let dir = tempfile::tempdir().unwrap();
    let s = demo::run_demo(&dir.path().join("demo"), &plan, &topology, &Quiet).unwrap();
    let shipped = s.shipped.expect("the built-in face has the shipped model");
    let base = &s.baseline;
    assert_eq!(
        shipped.samples,
        plan.test_subjects * plan.images_per_subject
    );
    assert_eq!((shipped.missing, shipped.pose_failures), (0, 0));
    eprintln!(
        "shipped: MAE_r {:.2} deg, MAE_t {:.2} mm, ADD {:.2} mm; mean pose: {:.2} deg, {:.2} mm, {:.2} mm",
        shipped.mae_r_deg,
        shipped.mae_t_mm,
        shipped.add_mm,
        base.mae_r_deg,
        base.mae_t_mm,
        base.add_mm
    );
    assert!(
        3.0 * shipped.mae_r_deg <= base.mae_r_deg,
        "MAE_r {:.2} deg is not a third of the mean pose's {:.2}",
        shipped.mae_r_deg,
        base.mae_r_deg
    );
    assert!(
        3.0 * shipped.add_mm <= base.add_mm,
        "ADD {:.2} mm is not a third of the mean pose's {:.2}",
        shipped.add_mm,
        base.add_mm
    );
    assert!(shipped.recon_mean_mm.is_some() && shipped.mask.is_some());
    // The demo's page and summary carry the row.
    let html = std::fs::read_to_string(&s.report).unwrap();
    assert!(
        html.contains("tiny PerspNet, shipped"),
        "no shipped row in the report"
    );
    assert!(dir.path().join("demo/shipped.parquet").exists());
}
