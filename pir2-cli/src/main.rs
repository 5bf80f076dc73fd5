//! The `pir2` binary: a thin argument parser over `pir2_cli`.

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand, ValueEnum};

use pir2_cli::demo::{self, DemoConfig, Policy};
use pir2_cli::leap_cmd;

#[derive(Parser, Debug)]
#[command(
    name = "pir2",
    version,
    about = "Reactive real-time flow policies (πR²)"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum PolicyArg {
    Pir2,
    Pir2Hidden,
    Pir2Full,
    Rtc,
    Flow,
}

impl From<PolicyArg> for Policy {
    fn from(p: PolicyArg) -> Self {
        match p {
            PolicyArg::Pir2 => Policy::PiR2,
            PolicyArg::Pir2Hidden => Policy::PiR2Hidden,
            PolicyArg::Pir2Full => Policy::PiR2Full,
            PolicyArg::Rtc => Policy::Rtc,
            PolicyArg::Flow => Policy::Flow,
        }
    }
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// The embedded default end to end: collect → train → evaluate every deployment mode.
    Demo {
        /// A smaller, faster run.
        #[arg(long)]
        quick: bool,
        /// TOML config (fields of `DemoConfig`); flags override it.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Output directory (must not exist or be empty; default: `runs/demo-<time>`).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Test episodes per cell.
        #[arg(long)]
        episodes: Option<usize>,
    },
    /// Collect expert demonstrations into a LeRobotDataset v3.0 directory.
    Collect {
        /// The task (leap-cube needs a build with `--features mujoco`).
        #[arg(value_parser = ["ballplate", "leap-cube"], default_value = "ballplate")]
        task: String,
        /// Dataset directory.
        #[arg(long)]
        out: PathBuf,
        /// leap-cube: expert seeds (episodes are stored seed-major).
        #[arg(long, value_delimiter = ',', default_value = "0,1,2,3")]
        seeds: Vec<u64>,
        /// leap-cube: episodes per expert seed.
        #[arg(long, default_value_t = 50)]
        per_seed: usize,
        /// leap-cube: the faster, weaker MPC expert.
        #[arg(long)]
        fast: bool,
        /// Episodes to keep.
        #[arg(long, default_value_t = 200)]
        episodes: usize,
        /// Seed.
        #[arg(long, default_value_t = 7)]
        seed: u64,
        /// Append the missing episodes to an existing dataset.
        #[arg(long, conflicts_with = "overwrite")]
        resume: bool,
        /// Replace an existing dataset.
        #[arg(long)]
        overwrite: bool,
    },
    /// Train one policy (candle MLP; leap-cube: U-Nets, all four study policies unless
    /// --policy) on a dataset; the checkpoint is picked in closed loop.
    Train {
        /// The task (leap-cube needs a build with `--features mujoco`).
        #[arg(value_parser = ["ballplate", "leap-cube"], default_value = "ballplate")]
        task: String,
        /// Dataset directory (LeRobotDataset v3.0).
        #[arg(long)]
        data: PathBuf,
        /// Which policy (required for ballplate).
        #[arg(long, value_enum)]
        policy: Option<PolicyArg>,
        /// Checkpoint directory (must not exist).
        #[arg(long)]
        out: PathBuf,
        /// TOML config (fields of `DemoConfig`: steps, lr, nfe, ...; leap-cube:
        /// `LeapStudyConfig`).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Evaluate a checkpoint in every mode that fits it, at each unit delay; leap-cube: run
    /// the deployment or horizon study (table, PNG, JSON).
    Eval {
        /// The task (leap-cube needs a build with `--features mujoco`).
        #[arg(value_parser = ["ballplate", "leap-cube"], default_value = "ballplate")]
        task: String,
        /// Checkpoint directory (leap-cube: the output of `pir2 train leap-cube`; policies
        /// missing there are trained).
        #[arg(long)]
        checkpoint: Option<PathBuf>,
        /// Which policy the checkpoint is (ballplate).
        #[arg(long, value_enum)]
        policy: Option<PolicyArg>,
        /// leap-cube: which study.
        #[arg(long, value_parser = ["deployment", "horizon"], default_value = "deployment")]
        study: String,
        /// leap-cube: TOML config (fields of `LeapStudyConfig`).
        #[arg(long)]
        config: Option<PathBuf>,
        /// leap-cube: dataset directory (overrides the config's).
        #[arg(long)]
        data: Option<PathBuf>,
        /// leap-cube: output directory (must not exist or be empty).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Unit delays.
        #[arg(long, value_delimiter = ',', default_value = "1,2,3")]
        d0: Vec<usize>,
        /// Episodes per cell (default 100; leap-cube: the config's).
        #[arg(long)]
        episodes: Option<usize>,
        /// Seed of the evaluation episodes.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Write the cells as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Send the action-head calls to `pir2 serve policy` at this Zenoh endpoint
        /// (e.g. `tcp/10.0.0.2:7447`; feature `remote`). The server must run the same
        /// checkpoint; locally only its normalisation is used.
        #[arg(long)]
        remote: Option<String>,
        /// With --remote: ms a request may take before it is sent again.
        #[arg(long, default_value_t = 200)]
        remote_timeout_ms: u64,
        /// With --remote: consecutive timeouts before the evaluation stops.
        #[arg(long, default_value_t = 25)]
        remote_max_failed: u32,
        /// With --remote: seconds to wait for the server at start.
        #[arg(long, default_value_t = 5.0)]
        connect_timeout: f64,
    },
    /// Run a policy stack on a robot (or its emulators).
    Run(pir2_cli::run::RunArgs),
    /// Servers for the remote slow channel and the remote action head (feature `remote`).
    Serve {
        #[command(subcommand)]
        cmd: pir2_cli::serve::ServeCmd,
    },
    /// Plot a demo result (`result.json`) or a run trace (`trace.json`) to PNG.
    Plot {
        /// Input JSON.
        input: PathBuf,
        /// Output PNG (default: next to the input).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Export a candle checkpoint (MLP or U-Net) to ONNX for ONNX Runtime deployment.
    Export {
        /// Checkpoint directory (config.json, stats.json, model.safetensors).
        checkpoint: PathBuf,
        /// Output ONNX file (must not exist).
        #[arg(long)]
        onnx: PathBuf,
    },
    /// Benchmarks printed side by side (schedule, runtime).
    Bench {
        /// What to measure.
        #[arg(value_parser = ["schedule", "runtime", "all"], default_value = "all")]
        what: String,
        /// Seconds per real-time run.
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
    },
    /// Robot tools: check a connection, run the emulators.
    Robot {
        #[command(subcommand)]
        cmd: RobotCmd,
    },
}

#[derive(Subcommand, Debug)]
enum RobotCmd {
    /// Connect, read state, report.
    Check {
        /// xArm controller address (command port 502 unless given as host:port).
        #[arg(long)]
        xarm: Option<String>,
        /// XHand serial device.
        #[arg(long)]
        xhand: Option<PathBuf>,
        /// Clear a latched xArm error/warning (collision, emergency stop) after reporting it.
        #[arg(long)]
        clear_errors: bool,
    },
    /// Run an emulator until Ctrl-C.
    Emulate {
        /// Which robot.
        #[arg(value_parser = ["xarm", "xhand"])]
        robot: String,
        /// Host to listen on (xarm).
        #[arg(long, default_value = "127.0.0.1")]
        host: IpAddr,
        /// Use a pseudo-terminal (xhand).
        #[arg(long)]
        pty: bool,
    },
}

fn load_demo_config(path: Option<&PathBuf>, quick: bool) -> Result<DemoConfig> {
    match path {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("reading config {}", p.display()))?;
            toml::from_str(&text).with_context(|| format!("parsing config {}", p.display()))
        }
        None => Ok(if quick {
            DemoConfig::quick()
        } else {
            DemoConfig::default()
        }),
    }
}

static INTERRUPTED: AtomicBool = AtomicBool::new(false);

extern "C" fn on_sigint(_: libc::c_int) {
    INTERRUPTED.store(true, Ordering::SeqCst);
}

/// A stop flag set by Ctrl-C (SIGINT), so emulators shut down and release their ports.
fn ctrl_c_flag() -> Arc<AtomicBool> {
    let stop = Arc::new(AtomicBool::new(false));
    // SAFETY: installs an async-signal-safe handler that only stores to an atomic.
    unsafe {
        libc::signal(libc::SIGINT, on_sigint as *const () as libc::sighandler_t);
    }
    let s = stop.clone();
    std::thread::spawn(move || loop {
        if INTERRUPTED.load(Ordering::SeqCst) {
            s.store(true, Ordering::SeqCst);
            return;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    });
    stop
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.cmd {
        Cmd::Demo {
            quick,
            config,
            out,
            episodes,
        } => {
            let mut cfg = load_demo_config(config.as_ref(), quick)?;
            if let Some(e) = episodes {
                cfg.episodes = e;
            }
            let out = out.unwrap_or_else(demo::default_out_dir);
            println!(
                "pir2 demo → {}  ({} demos, {} steps/policy, {} episodes/cell, seeds {:?})",
                out.display(),
                cfg.demos,
                cfg.train_steps,
                cfg.episodes,
                cfg.seeds
            );
            let r = demo::run(&cfg, &out)?;
            println!(
                "\n{}",
                pir2_cli::study::table(&r.cells, &r.labels, &r.config.d0s)
            );
            for (stage, s) in &r.timings {
                println!("{stage:>9}: {s:6.1} s");
            }
            println!(
                "wrote {}/result.json, table.md, success.png, dataset/, checkpoints/",
                out.display()
            );
        }
        Cmd::Collect {
            task,
            out,
            episodes,
            seed,
            resume,
            overwrite,
            seeds,
            per_seed,
            fast,
        } => {
            let mode = if resume {
                pir2_sim::dataset::WriteMode::Resume
            } else if overwrite {
                pir2_sim::dataset::WriteMode::Overwrite
            } else {
                pir2_sim::dataset::WriteMode::New
            };
            if task == "leap-cube" {
                return leap_cmd::collect(&out, &seeds, per_seed, mode, fast);
            }
            let eps = demo::collect(episodes, seed, true)?;
            demo::write_dataset(&out, &eps, mode)?;
            println!("wrote {} episodes to {}", eps.len(), out.display());
        }
        Cmd::Train {
            task,
            data,
            policy,
            out,
            config,
            seed,
        } => {
            if task == "leap-cube" {
                let args = leap_cmd::LeapArgs {
                    config: config.as_deref(),
                    data: Some(&data),
                    ..Default::default()
                };
                let p = policy.and_then(|p| p.to_possible_value());
                let ps: Vec<&str> = p.iter().map(|p| p.get_name()).collect();
                return leap_cmd::train(&args, &ps, &out);
            }
            let policy = policy.context("--policy is required for ballplate")?;
            if out.exists() {
                bail!(
                    "checkpoint directory {} already exists; choose another --out",
                    out.display()
                );
            }
            let cfg = load_demo_config(config.as_ref(), false)?;
            let ds = pir2_sim::dataset::read_dataset(&data)
                .with_context(|| format!("reading dataset {}", data.display()))?;
            let pb = indicatif::ProgressBar::new(cfg.train_steps as u64);
            let (model, scores) = demo::train_policy(
                &ds.episodes,
                policy.into(),
                seed,
                &cfg,
                Some(&out.join("steps")),
                &pb,
            )?;
            pb.finish();
            model.save(&out.join("best"))?;
            println!("closed-loop validation (step, success): {scores:?}");
            println!("best checkpoint: {}", out.join("best").display());
        }
        Cmd::Eval {
            task,
            checkpoint,
            policy,
            study,
            config,
            data,
            out,
            d0,
            episodes,
            seed,
            json,
            remote,
            remote_timeout_ms,
            remote_max_failed,
            connect_timeout,
        } => {
            if task == "leap-cube" {
                let args = leap_cmd::LeapArgs {
                    config: config.as_deref(),
                    data: data.as_deref(),
                    pretrained: checkpoint.as_deref(),
                    episodes,
                };
                let out = out.context("--out is required for leap-cube")?;
                return leap_cmd::eval(&study, &args, &out);
            }
            let checkpoint = checkpoint.context("--checkpoint is required for ballplate")?;
            let policy: Policy = policy.context("--policy is required for ballplate")?.into();
            let episodes = episodes.unwrap_or(100);
            if let Some(p) = json.as_ref().filter(|p| p.exists()) {
                bail!("{} already exists; choose another --json path", p.display());
            }
            let model = pir2_backends::candle::CandleModel::load(&checkpoint)
                .with_context(|| format!("loading {}", checkpoint.display()))?;
            let remote = match remote {
                Some(ep) => {
                    let r = pir2_cli::serve::RemotePolicy::connect(
                        &ep,
                        std::time::Duration::from_millis(remote_timeout_ms.max(1)),
                        std::time::Duration::from_secs_f64(connect_timeout.max(0.0)),
                        remote_max_failed.max(1),
                    )?;
                    eprintln!("connected to the policy server at {ep}");
                    Some(r)
                }
                None => None,
            };
            let cfg = DemoConfig::default();
            let mut cells = Vec::new();
            let rows: Vec<_> = demo::rows(&cfg)
                .into_iter()
                .filter(|r| r.policy == policy)
                .collect();
            for row in &rows {
                for &d in &d0 {
                    let (ok, overruns) = match &remote {
                        Some(r) => r.closed_loop(
                            &model,
                            policy,
                            &row.mode,
                            d,
                            episodes,
                            seed,
                            cfg.threads,
                        )?,
                        None => demo::closed_loop(
                            &model,
                            policy,
                            &row.mode,
                            d,
                            episodes,
                            seed,
                            cfg.threads,
                            &|| {},
                        )?,
                    };
                    cells.push(pir2_cli::study::Cell {
                        label: row.label.clone(),
                        d0: d,
                        seed,
                        successes: ok,
                        episodes,
                        overruns,
                    });
                }
            }
            let labels: Vec<String> = rows.iter().map(|r| r.label.clone()).collect();
            println!("{}", pir2_cli::study::table(&cells, &labels, &d0));
            if let Some(r) = &remote {
                eprintln!("{}", r.report());
            }
            if let Some(p) = json {
                std::fs::write(&p, serde_json::to_string_pretty(&cells)?)?;
            }
        }
        Cmd::Run(args) => {
            let summary = pir2_cli::run::run(&args, ctrl_c_flag())?;
            print!("{summary}");
            if let Some(p) = &args.json {
                std::fs::write(p, serde_json::to_string_pretty(&summary)?)
                    .with_context(|| format!("writing {}", p.display()))?;
            }
        }
        Cmd::Serve { cmd } => pir2_cli::serve::serve(&cmd, ctrl_c_flag())?,
        Cmd::Plot { input, out } => {
            let text = std::fs::read_to_string(&input)
                .with_context(|| format!("reading {}", input.display()))?;
            let v: serde_json::Value = serde_json::from_str(&text)
                .with_context(|| format!("parsing {}", input.display()))?;
            let out = out.unwrap_or_else(|| input.with_extension("png"));
            if out.exists() {
                bail!(
                    "{} already exists; choose another path with --out",
                    out.display()
                );
            }
            if v.get("cells").is_some() {
                let r: demo::DemoResult = serde_json::from_value(v)?;
                let series = pir2_cli::study::to_series(&r.cells, &r.labels, &r.config.d0s);
                pir2_cli::plot::plot_series(
                    &out,
                    "success vs unit delay",
                    "unit delay d0 (ticks)",
                    "success rate",
                    &series,
                )?;
            } else if v.get("calls").is_some() {
                let t: pir2_runtime::RunTrace = serde_json::from_value(v)?;
                pir2_cli::plot::plot_trace(&out, &t)?;
            } else {
                bail!(
                    "{} is neither a demo result (cells) nor a run trace (calls)",
                    input.display()
                );
            }
            println!("wrote {}", out.display());
        }
        Cmd::Export { checkpoint, onnx } => {
            if onnx.exists() {
                bail!(
                    "{} already exists; choose another --onnx path",
                    onnx.display()
                );
            }
            let ck = pir2_backends::checkpoint::Checkpoint::load(&checkpoint)
                .with_context(|| format!("loading checkpoint {}", checkpoint.display()))?;
            pir2_backends::onnx::candle_bridge::export_checkpoint(&ck, &onnx)
                .with_context(|| format!("exporting {} to ONNX", checkpoint.display()))?;
            println!("wrote {}", onnx.display());
        }
        Cmd::Bench { what, seconds } => {
            if what == "schedule" || what == "all" {
                print!("{}", pir2_cli::bench::schedule()?);
            }
            if what == "runtime" || what == "all" {
                print!("{}", pir2_cli::bench::runtime(seconds)?);
            }
        }
        Cmd::Robot { cmd } => match cmd {
            RobotCmd::Check {
                xarm,
                xhand,
                clear_errors,
            } => {
                let addr = match xarm {
                    None => None,
                    Some(s) => Some(match s.parse::<SocketAddr>() {
                        Ok(a) => a,
                        Err(_) => SocketAddr::new(
                            s.parse::<IpAddr>()
                                .with_context(|| format!("bad --xarm address {s}"))?,
                            502,
                        ),
                    }),
                };
                let mut opts = pir2_robots::CheckOptions::new(addr, xhand.as_deref());
                opts.clear_errors = clear_errors;
                let report = pir2_robots::check_with(&opts)?;
                println!("{report}");
            }
            RobotCmd::Emulate { robot, host, pty } => {
                let stop = ctrl_c_flag();
                if robot == "xarm" {
                    println!("xArm emulator on {host}: ports 502, 30001-30003 (Ctrl-C to stop)");
                    pir2_robots::run_xarm_emulator(host, pir2_robots::XArmPorts::standard(), stop)?;
                } else {
                    if !pty {
                        bail!("the XHand emulator needs --pty (a pseudo-terminal other programs can open)");
                    }
                    let path = pir2_robots::run_xhand_emulator_pty(stop.clone())?;
                    println!("XHand emulator on {} (Ctrl-C to stop)", path.display());
                    while !stop.load(Ordering::SeqCst) {
                        std::thread::sleep(std::time::Duration::from_millis(200));
                    }
                }
            }
        },
    }
    Ok(())
}
