//! Run the Leap-cube pipeline until `pir2 collect/eval leap-cube` is wired (feature `mujoco`):
//!
//! ```text
//! leap_study collect <dataset-dir> <per-seed> <seed>...   (resumable, fast MPC expert)
//! leap_study deployment|horizon <out-dir> [config.toml]
//! ```

#[cfg(feature = "mujoco")]
fn main() -> anyhow::Result<()> {
    use pir2_cli::leap::{
        collect_leap, result_table, study_deployment, study_horizon, LeapStudyConfig,
    };
    use std::path::Path;
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: leap_study collect <dir> <per-seed> <seed>... | leap_study deployment|horizon <out> [config.toml]";
    match args.first().map(String::as_str) {
        Some("collect") if args.len() >= 4 => {
            let per_seed: usize = args[2].parse()?;
            let fast = args.iter().any(|a| a == "--fast");
            let seeds: Vec<u64> = args[3..]
                .iter()
                .filter(|a| *a != "--fast")
                .map(|s| s.parse())
                .collect::<Result<_, _>>()?;
            let t = std::time::Instant::now();
            let s = collect_leap(
                Path::new(&args[1]),
                &seeds,
                per_seed,
                pir2_sim::dataset::WriteMode::Resume,
                fast,
            )?;
            println!("{s:?} in {:.1} s", t.elapsed().as_secs_f64());
        }
        Some(study @ ("deployment" | "horizon")) if args.len() >= 2 => {
            let cfg: LeapStudyConfig = match args.get(2) {
                Some(p) => toml::from_str(&std::fs::read_to_string(p)?)?,
                None => LeapStudyConfig::default(),
            };
            let out = Path::new(&args[1]);
            let r = if study == "deployment" {
                study_deployment(&cfg, out)?
            } else {
                study_horizon(&cfg, out)?
            };
            println!("{}", result_table(&r));
            println!("demos {} timings {:?}", r.demos, r.timings);
            println!("validation {:?}", r.validation);
        }
        _ => anyhow::bail!("{usage}"),
    }
    Ok(())
}

#[cfg(not(feature = "mujoco"))]
fn main() {
    eprintln!("leap_study needs --features mujoco");
}
