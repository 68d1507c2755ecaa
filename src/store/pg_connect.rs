//! Opening a connection to the cluster database: each host of the URL in turn, each under its
//! own deadline for the whole opening (socket, startup, authentication, the read-write check).
//!
//! tokio-postgres's `connect_timeout` bounds only the socket's connect. A frozen primary
//! (`docker pause`, a stopped VM, a process stuck in the kernel) still completes TCP handshakes
//! and acknowledges the startup message from its kernel, so an opening through it waited without
//! end, holding up the hosts after it in the URL: no new connection reached the new primary
//! while the old one was frozen (issue #34's T4c). libpq's `connect_timeout` bounds the whole
//! opening of each host; this is that.
//!
//! The order: the host that last gave a read-write connection first (the primary of now, found
//! without waiting on the others), then the others in the URL's order, and last any host that
//! timed out in the last [`SUSPECT_FOR`]. So after a failover each new connection goes straight
//! to the new primary instead of waiting out a frozen host listed before it, and a frozen old
//! primary that thaws still writable (until Patroni demotes it) is not taken before the new one.
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
use std::time::{Duration, Instant};
use tokio::task::JoinHandle;
use tokio_postgres::{Client, Config, NoTls};

/// The default bound of one host's opening when the URL sets no `connect_timeout`.
pub(super) const DEFAULT_HOST_DEADLINE: Duration = Duration::from_secs(5);

/// How long a host that did not complete an opening in time is tried after the others.
pub(super) const SUSPECT_FOR: Duration = Duration::from_secs(30);

/// One configuration per host of a multi-host URL, tried in the order above.
pub(super) struct PerHost {
    hosts: Vec<Config>,
    deadline: Duration,
    /// The host that last gave a connection (usize::MAX: none yet).
    preferred: AtomicUsize,
    /// When each host last ran out of time.
    timed_out: parking_lot::Mutex<Vec<Option<Instant>>>,
}

impl PerHost {
    /// Splits `config` into one configuration per host (every other setting kept), each opening
    /// bounded by the URL's `connect_timeout` (else [`DEFAULT_HOST_DEADLINE`]).
    pub(super) fn new(config: &Config) -> Self {
        let deadline = config.get_connect_timeout().copied().unwrap_or(DEFAULT_HOST_DEADLINE);
        let n = config.get_hosts().len().max(config.get_hostaddrs().len());
        let hosts = (0..n).map(|i| single_host(config, i)).collect();
        Self {
            hosts,
            deadline,
            preferred: AtomicUsize::new(usize::MAX),
            timed_out: parking_lot::Mutex::new(vec![None; n]),
        }
    }

    /// The hosts' indices in the order they are tried now.
    fn order(&self) -> Vec<usize> {
        let timed_out = self.timed_out.lock();
        let suspect = |i: usize| timed_out[i].is_some_and(|t| t.elapsed() < SUSPECT_FOR);
        let preferred = self.preferred.load(Relaxed);
        let mut order: Vec<usize> = (0..self.hosts.len()).collect();
        // Stable: the URL's order within each rank.
        order.sort_by_key(|&i| (suspect(i), i != preferred));
        order
    }
}

/// The `i`th host of `config` with every other setting of it.
fn single_host(config: &Config, i: usize) -> Config {
    let mut c = Config::new();
    if let Some(host) = config.get_hosts().get(i) {
        match host {
            tokio_postgres::config::Host::Tcp(h) => c.host(h),
            #[cfg(unix)]
            tokio_postgres::config::Host::Unix(p) => c.host_path(p),
        };
    }
    if let Some(addr) = config.get_hostaddrs().get(i) {
        c.hostaddr(*addr);
    }
    let ports = config.get_ports();
    if let Some(&port) = ports.get(i).or_else(|| ports.first()) {
        c.port(port);
    }
    if let Some(v) = config.get_user() {
        c.user(v);
    }
    if let Some(v) = config.get_password() {
        c.password(v);
    }
    if let Some(v) = config.get_dbname() {
        c.dbname(v);
    }
    if let Some(v) = config.get_options() {
        c.options(v);
    }
    if let Some(v) = config.get_application_name() {
        c.application_name(v);
    }
    if let Some(&v) = config.get_connect_timeout() {
        c.connect_timeout(v);
    }
    if let Some(&v) = config.get_tcp_user_timeout() {
        c.tcp_user_timeout(v);
    }
    c.ssl_mode(config.get_ssl_mode())
        .ssl_negotiation(config.get_ssl_negotiation())
        .keepalives(config.get_keepalives())
        .keepalives_idle(config.get_keepalives_idle())
        .target_session_attrs(config.get_target_session_attrs())
        .channel_binding(config.get_channel_binding());
    if let Some(v) = config.get_keepalives_interval() {
        c.keepalives_interval(v);
    }
    if let Some(v) = config.get_keepalives_retries() {
        c.keepalives_retries(v);
    }
    c
}

impl deadpool_postgres::Connect for PerHost {
    fn connect(
        &self,
        _whole: &Config,
    ) -> futures::future::BoxFuture<'_, Result<(Client, JoinHandle<()>), tokio_postgres::Error>> {
        Box::pin(async move {
            let mut last = None;
            for i in self.order() {
                match tokio::time::timeout(self.deadline, self.hosts[i].connect(NoTls)).await {
                    Ok(Ok((client, connection))) => {
                        self.preferred.store(i, Relaxed);
                        self.timed_out.lock()[i] = None;
                        let task = tokio::spawn(async move {
                            if let Err(e) = connection.await {
                                tracing::debug!(error = %e, "a cluster database connection ended");
                            }
                        });
                        return Ok((client, task));
                    }
                    // A standby (not read-write), a refused or unreachable host: the next one.
                    Ok(Err(e)) => last = Some(e),
                    Err(_) => {
                        self.timed_out.lock()[i] = Some(Instant::now());
                        tracing::warn!(
                            host = i,
                            deadline = ?self.deadline,
                            "a cluster database host did not complete a connection in time (frozen or cut off); trying the next"
                        );
                        // tokio-postgres's own timeout error (public, though hidden from its docs):
                        // the pool reads it as a backend error, answered Unavailable.
                        last = Some(tokio_postgres::Error::__private_api_timeout());
                    }
                }
            }
            Err(last.unwrap_or_else(tokio_postgres::Error::__private_api_timeout))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_multi_host_url_splits_into_one_config_per_host_with_every_setting() {
        let url = "postgres://u:pw@pg1:5433,pg2,pg3:5435/db?target_session_attrs=read-write&connect_timeout=2\
                   &application_name=loopd&keepalives_idle=7";
        let config: Config = url.parse().expect("a valid URL");
        let per = PerHost::new(&config);
        assert_eq!(per.hosts.len(), 3);
        assert_eq!(per.deadline, Duration::from_secs(2));
        let hosts: Vec<_> = per.hosts.iter().map(|c| (c.get_hosts().to_vec(), c.get_ports().to_vec())).collect();
        assert_eq!(hosts[0].0, vec![tokio_postgres::config::Host::Tcp("pg1".into())]);
        assert_eq!(hosts[0].1, vec![5433]);
        assert_eq!(hosts[1].1, vec![5432], "a host without a port takes the default");
        assert_eq!(hosts[2].1, vec![5435]);
        for c in &per.hosts {
            assert_eq!(c.get_user(), Some("u"));
            assert_eq!(c.get_password(), Some(&b"pw"[..]));
            assert_eq!(c.get_dbname(), Some("db"));
            assert_eq!(c.get_application_name(), Some("loopd"));
            assert_eq!(c.get_keepalives_idle(), Duration::from_secs(7));
            assert_eq!(c.get_target_session_attrs(), tokio_postgres::config::TargetSessionAttrs::ReadWrite);
        }
        let plain: Config = "postgres://u@pg1/db".parse().expect("a valid URL");
        assert_eq!(PerHost::new(&plain).deadline, DEFAULT_HOST_DEADLINE);
    }

    #[test]
    fn the_last_primary_goes_first_and_a_host_that_timed_out_last() {
        let config: Config = "postgres://u@pg1,pg2,pg3/db".parse().expect("a valid URL");
        let per = PerHost::new(&config);
        assert_eq!(per.order(), [0, 1, 2], "the URL's order at first");
        per.preferred.store(2, Relaxed);
        assert_eq!(per.order(), [2, 0, 1]);
        per.timed_out.lock()[0] = Some(Instant::now());
        assert_eq!(per.order(), [2, 1, 0]);
        per.timed_out.lock()[2] = Some(Instant::now());
        assert_eq!(per.order(), [1, 2, 0], "a preferred host that timed out goes after the others");
        per.timed_out.lock()[0] = Instant::now().checked_sub(SUSPECT_FOR * 2);
        assert_eq!(per.order(), [0, 1, 2], "a timeout long ago no longer counts");
    }
}
