//! The robot side of a remote policy (feature `remote`): the TLS options every remote
//! channel takes ([`TlsOptions`], shared by `pir2 serve`, `pir2 gr00t run|serve` and `pir2
//! eval --remote`) and the connection `pir2 eval --remote` evaluates through ([`RemotePolicy`]).
//!
//! Transport, wire format and fault handling are `pir2_runtime::remote`'s. This module sits
//! below both the servers ([`crate::serve`]) and the task commands ([`crate::tasks`]), which
//! import it; it imports neither.

use std::path::PathBuf;

use anyhow::Result;

use pir2_backends::candle::CandleModel;

use crate::study::pipeline::Models;

/// Mutual TLS for the remote channels (all three files or none) and the explicit
/// `--insecure` for a server listening beyond this machine without TLS
/// (`--tls-ca/--tls-cert/--tls-key`, `--insecure`).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct TlsOptions {
    /// The CA (PEM) both sides trust; with --tls-cert and --tls-key, endpoints are
    /// `tls/HOST:PORT` and both sides verify each other (mutual TLS).
    #[arg(long = "tls-ca", id = "tls_ca", value_name = "TLS_CA", requires_all = ["tls_cert", "tls_key"])]
    pub ca: Option<PathBuf>,
    /// This side's certificate (PEM), signed by --tls-ca.
    #[arg(long = "tls-cert", id = "tls_cert", value_name = "TLS_CERT", requires_all = ["tls_ca", "tls_key"])]
    pub cert: Option<PathBuf>,
    /// This side's private key (PEM).
    #[arg(long = "tls-key", id = "tls_key", value_name = "TLS_KEY", requires_all = ["tls_ca", "tls_cert"])]
    pub key: Option<PathBuf>,
    /// Listen on (servers) or connect to (robots, `eval --remote`) a non-loopback address
    /// without TLS, for a trusted lab network only. Anyone on that network can then read the
    /// features, query the policy, impersonate the server or answer the robot's requests.
    #[arg(long)]
    pub insecure: bool,
}

#[cfg(feature = "remote")]
impl TlsOptions {
    /// `link` with these TLS files, checked: a `tls/…` endpoint needs the files (readable
    /// PEM, [`pir2_runtime::remote::TlsFiles::check`]), and a non-loopback address without
    /// TLS is refused, to listen on or to connect to, unless
    /// `insecure` (then it says so loudly on stderr).
    pub fn apply(&self, link: pir2_runtime::remote::Link) -> Result<pir2_runtime::remote::Link> {
        let link = match (&self.ca, &self.cert, &self.key) {
            (Some(ca), Some(cert), Some(key)) => link.with_tls(pir2_runtime::remote::TlsFiles {
                ca: ca.clone(),
                cert: cert.clone(),
                key: key.clone(),
            }),
            (None, None, None) => link,
            _ => anyhow::bail!("--tls-ca, --tls-cert and --tls-key go together: give all three"),
        };
        link.check_exposure(self.insecure)?;
        // An unreadable or garbled file is named now, before anything is loaded or dialled.
        if let Some(t) = &link.tls {
            t.check()?;
        }
        if self.insecure && link.check_exposure(false).is_err() {
            eprintln!(
                "WARNING: --insecure: talking WITHOUT TLS beyond this machine (listen {:?}, \
                 connect {:?}). Anyone who can reach these addresses can read the features, \
                 query the policy, impersonate the server or answer the robot's requests.",
                link.listen, link.connect
            );
        }
        Ok(link)
    }
}

#[cfg(not(feature = "remote"))]
pub(crate) const NO_REMOTE: &str = "this pir2 was built without the Zenoh transport: rebuild with \
                         `cargo build --release -p pir2-cli --features remote`";

/// The robot side of `pir2 eval --remote`: a connection to `pir2 serve policy`.
pub struct RemotePolicy {
    #[cfg(feature = "remote")]
    inner: imp::RemotePolicy,
}

impl std::fmt::Debug for RemotePolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemotePolicy").finish_non_exhaustive()
    }
}

impl RemotePolicy {
    /// Connect to `endpoint` (a Zenoh locator such as `tcp/10.0.0.2:7447`), waiting up to
    /// `connect_timeout` for the server; each request may take `timeout` before it is sent
    /// again, and `max_failed` timeouts in a row stop the evaluation.
    #[allow(unused_variables)]
    pub fn connect(
        endpoint: &str,
        tls: &TlsOptions,
        timeout: std::time::Duration,
        connect_timeout: std::time::Duration,
        max_failed: u32,
    ) -> Result<Self> {
        #[cfg(feature = "remote")]
        return Ok(Self {
            inner: imp::RemotePolicy::connect(endpoint, tls, timeout, connect_timeout, max_failed)?,
        });
        #[cfg(not(feature = "remote"))]
        anyhow::bail!("--remote: {NO_REMOTE}")
    }

    /// The server as a model factory for the one closed loop
    /// ([`crate::study::pipeline::closed_loop`]): every model made shares this connection;
    /// `local` supplies only the output (denormalisation) map and must be the checkpoint the
    /// server runs.
    #[allow(unused_variables)]
    pub fn models(&self, local: &CandleModel) -> Models<'_> {
        let output = crate::study::pipeline::output_map(local);
        #[cfg(feature = "remote")]
        return self.inner.models(output);
        #[cfg(not(feature = "remote"))]
        unreachable!("a RemotePolicy exists only in a build with feature `remote`")
    }

    /// Refuse the server unless it runs the checkpoint `dir` (loaded as `local`) as
    /// `policy`, by the identity it announced ([`crate::identity::expect_server`]).
    #[allow(unused_variables)]
    pub fn expect_checkpoint(
        &self,
        local: &CandleModel,
        dir: &std::path::Path,
        policy: pir2_runtime::Policy,
    ) -> Result<()> {
        #[cfg(feature = "remote")]
        return self.inner.expect_checkpoint(local, dir, policy);
        #[cfg(not(feature = "remote"))]
        unreachable!("a RemotePolicy exists only in a build with feature `remote`")
    }

    /// A line naming the server and its counters, for errors of an evaluation through it.
    pub fn context(&self) -> String {
        #[cfg(feature = "remote")]
        return self.inner.context();
        #[cfg(not(feature = "remote"))]
        String::new()
    }

    /// One line of counters (calls, attempts, timeouts, reconnects, last round trip).
    pub fn report(&self) -> String {
        #[cfg(feature = "remote")]
        return self.inner.report();
        #[cfg(not(feature = "remote"))]
        String::new()
    }
}

#[cfg(feature = "remote")]
mod imp {
    use std::sync::{Arc, Mutex};
    use std::time::Duration;

    use anyhow::{Context, Result};

    use pir2_backends::candle::CandleModel;
    use pir2_runtime::remote::{Link, RemoteModel, RemoteModelConfig, RemoteStats};
    use pir2_runtime::{ModelInput, OutputMap, VelocityModel};

    use crate::study::pipeline::Models;

    /// One connection shared by every evaluation thread (the server answers one request at a
    /// time anyway).
    #[derive(Clone)]
    struct Shared(Arc<Mutex<RemoteModel>>);

    impl VelocityModel for Shared {
        fn backend(&self) -> &'static str {
            "remote"
        }
        fn velocity(
            &mut self,
            input: &ModelInput<'_>,
            out: &mut [f32],
        ) -> pir2_runtime::Result<()> {
            self.0
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .velocity(input, out)
        }
    }

    pub(super) struct RemotePolicy {
        model: Shared,
        stats: Arc<RemoteStats>,
        endpoint: String,
        identity: Option<String>,
    }

    impl RemotePolicy {
        pub(super) fn connect(
            endpoint: &str,
            tls: &super::TlsOptions,
            timeout: Duration,
            connect_timeout: Duration,
            max_failed: u32,
        ) -> Result<Self> {
            let cfg = RemoteModelConfig {
                link: tls.apply(Link::connect(endpoint))?,
                timeout,
                max_failed_calls: max_failed,
                connect_timeout,
                ..Default::default()
            };
            let m = RemoteModel::connect(cfg).with_context(|| {
                format!("connecting to the policy server at {endpoint} (is `pir2 serve policy` running there?)")
            })?;
            Ok(Self {
                stats: m.stats(),
                identity: m.server_identity().map(str::to_owned),
                model: Shared(Arc::new(Mutex::new(m))),
                endpoint: endpoint.to_string(),
            })
        }

        pub(super) fn expect_checkpoint(
            &self,
            local: &CandleModel,
            dir: &std::path::Path,
            policy: pir2_runtime::Policy,
        ) -> Result<()> {
            crate::identity::expect_server(
                self.identity.as_deref(),
                &self.endpoint,
                local,
                dir,
                policy,
            )
        }

        pub(super) fn models(&self, output: OutputMap) -> Models<'_> {
            Models::new(output, move || Box::new(self.model.clone()))
        }

        pub(super) fn context(&self) -> String {
            format!(
                "evaluating with the policy server at {} (counters: {:?})",
                self.endpoint,
                self.stats.counters()
            )
        }

        pub(super) fn report(&self) -> String {
            let c = self.stats.counters();
            format!(
                "remote policy {}: calls {} attempts {} timeouts {} reconnects {} failed calls {} \
                 foreign replies {} last rtt {} µs",
                self.endpoint,
                c.calls,
                c.attempts,
                c.timeouts,
                c.reconnects,
                c.failed_calls,
                c.foreign_replies,
                c.last_rtt_ns / 1000
            )
        }
    }
}
