//! Diagnose the demo pipeline on one policy: train a standard-flow MLP, print the open-loop
//! error of sampled vs expert actions on demonstration frames, then run one closed-loop
//! episode printing the actions.
//! Run: `cargo run --release -p pir2-cli --example debug_demo -- [demo.toml]`
use pir2_backends::candle::CandleModel;
use pir2_cli::study::ballplate::{collect, BallPlateTask, DemoConfig};
use pir2_cli::study::pipeline::{output_map, train_policy};
use pir2_runtime::*;

/// A copy of a model for another head (same weights, own scratch).
fn clone_model(m: &CandleModel) -> anyhow::Result<CandleModel> {
    let mut c = CandleModel::new(m.config().clone(), m.stats().clone(), 0)?;
    c.restore(&m.snapshot()?)?;
    Ok(c)
}

use pir2_sim::ballplate::{BallPlate, BallPlateConfig};
fn main() -> anyhow::Result<()> {
    let cfg: DemoConfig = match std::env::args().nth(1) {
        Some(p) => toml::from_str(&std::fs::read_to_string(p)?)?,
        None => DemoConfig::quick(),
    };
    let demos = collect(50, 7, false)?;
    println!(
        "demo lens {:?}",
        demos.iter().take(5).map(|e| e.len()).collect::<Vec<_>>()
    );
    println!(
        "action0 {:?} fast0 {:?} slow0 {:?}",
        demos[0].action(0),
        demos[0].fast(0),
        demos[0].slow(0)
    );
    let task = BallPlateTask::new(cfg);
    let (m, scores) = train_policy(&task, &demos, Policy::Flow, 0, None, &|_| {})?;
    println!("scores {scores:?} out {:?}", output_map(&m));
    // Open loop: the model's first sampled action vs the expert's label on demo frames.
    let mut mm = clone_model(&m)?;
    let mut rng = pir2_schedule::Rng::new(3);
    let mut err = 0.0f64;
    let mut base = 0.0f64;
    let mut n = 0;
    for e in demos.iter().take(5) {
        for t in (5..e.len()).step_by(37) {
            let mut hist = Vec::new();
            hist.extend_from_slice(e.fast(t - 1));
            hist.extend_from_slice(e.fast(t));
            let chunk = mm.sample_euler(
                &hist,
                pir2_runtime::SlowInput::Vector {
                    data: e.slow(t),
                    dim: pir2_sim::ballplate::SLOW_DIM,
                },
                0,
                10,
                &mut rng,
            )?;
            for j in 0..2 {
                err += ((chunk[j] - e.action(t)[j]) as f64).powi(2);
                base += (e.action(t)[j] as f64).powi(2);
            }
            n += 2;
            if n <= 8 {
                println!("t {t}: model {:?} expert {:?}", &chunk[..2], e.action(t));
            }
        }
    }
    println!(
        "open-loop rmse {:.4}  (rms of labels {:.4})",
        (err / n as f64).sqrt(),
        (base / n as f64).sqrt()
    );
    let task = BallPlateConfig::default();
    let mut env = BallPlate::new(task.clone())?;
    let mode = Mode::NaiveAsync {
        steps: 10,
        ensemble: None,
    };
    let spec = HeadSpec {
        horizon: 16,
        action_dim: 2,
        n_obs: 2,
        fast_dim: 6,
        slow_dim: pir2_sim::ballplate::SLOW_DIM,
        period: 20_000_000,
        d_max: 6,
        d_vis_max: 3,
    };
    let mut head = ActionHead::new(
        clone_model(&m)?,
        spec,
        mode.head_mode(10),
        LatencyWindow::new(20, 0, spec.period, 6),
        1,
    )?;
    let mut drv = LockstepDriver::new(&head).with_output(output_map(&m));
    let r = drv.run_episode(
        &mut env,
        &mut head,
        &mode,
        LockstepTiming::for_mode(&mode, 1),
        5,
        |t, a| {
            if t < 10 || t % 50 == 0 {
                println!("t {t} a {a:?}")
            }
        },
    )?;
    println!("steps {} success {}", r.steps, r.success);
    Ok(())
}
