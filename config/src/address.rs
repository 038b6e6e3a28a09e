//! A node's address as the config writes it: `IP:PORT`, `HOST:PORT` (a
//! host name, looked up where the node starts) or a host template such as
//! `{host:0}:7400`, the first host of the launcher's node list (Slurm's) or
//! of `launch.hosts`. Templates may sit inside a name (`{host:2}-ib:7400`).
//!
//! Checking an address ([`NodeAddress::parse`]) needs no network, so a
//! config for other hosts can be checked, and its certificates made, on a
//! laptop; [`NodeAddress::resolve`] fills the templates and looks the name up.

use std::net::{IpAddr, SocketAddr, ToSocketAddrs};

/// An address of the config, checked but not looked up.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NodeAddress {
    /// The host: an IP, a host name, or text with `{host:N}` templates.
    host: String,
    port: u16,
}

impl NodeAddress {
    /// Parses `HOST:PORT`; IPv6 literals go in brackets (`[::1]:7000`).
    pub fn parse(text: &str) -> Result<NodeAddress, String> {
        let form = || {
            format!(
                "{text:?} is not an address of the form HOST:PORT, where HOST is an IP, \
                 a host name or a host template such as {{host:0}} (e.g. 127.0.0.1:7000, \
                 node1:7000, {{host:0}}:7000)"
            )
        };
        if let Ok(a) = text.parse::<SocketAddr>() {
            return Ok(NodeAddress {
                host: a.ip().to_string(),
                port: a.port(),
            });
        }
        let (host, port) = text.rsplit_once(':').ok_or_else(form)?;
        let port: u16 = port.parse().map_err(|_| form())?;
        // A template's text must also be a valid name once filled: check
        // it with each template replaced by a stand-in label.
        let mut rest = host;
        let mut stand_in = String::new();
        while let Some(open) = rest.find('{') {
            stand_in.push_str(&rest[..open]);
            let close = rest[open..].find('}').ok_or_else(form)? + open;
            template_index(&rest[open..=close]).ok_or_else(|| {
                format!(
                    "{text:?}: {:?} is not a host template (write {{host:N}}, N from 0)",
                    &rest[open..=close]
                )
            })?;
            stand_in.push('h');
            rest = &rest[close + 1..];
        }
        stand_in.push_str(rest);
        if !is_host_name(&stand_in) {
            return Err(form());
        }
        Ok(NodeAddress {
            host: host.to_string(),
            port,
        })
    }

    /// The port.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// The largest N of the `{host:N}` templates, if any.
    pub fn most_host_index(&self) -> Option<usize> {
        templates(&self.host).map(|(_, n, _)| n).max()
    }

    /// The host with every template filled from `hosts`; `from` says where
    /// the list came from, for the error when it is too short or empty.
    pub fn host(&self, hosts: &[String], from: &str) -> Result<String, String> {
        let mut out = String::new();
        let mut rest = self.host.as_str();
        for (start, n, end) in templates(&self.host) {
            let Some(h) = hosts.get(n) else {
                return Err(if hosts.is_empty() {
                    format!(
                        "{{host:{n}}} needs a list of hosts: set launch.hosts, or start the \
                         node under Slurm (SLURM_STEP_NODELIST or SLURM_JOB_NODELIST)"
                    )
                } else {
                    format!(
                        "{{host:{n}}} names host {n} (from 0), but {from} lists {}: {}",
                        hosts.len(),
                        hosts.join(",")
                    )
                });
            };
            let before = &self.host[self.host.len() - rest.len()..start];
            out.push_str(before);
            out.push_str(h);
            rest = &self.host[end..];
        }
        out.push_str(rest);
        Ok(out)
    }

    /// The socket address: templates filled from `hosts`, then an IP as it
    /// is or a name looked up (its first address).
    pub fn resolve(&self, hosts: &[String], from: &str) -> Result<SocketAddr, String> {
        let host = self.host(hosts, from)?;
        if let Ok(ip) = host.parse::<IpAddr>() {
            return Ok(SocketAddr::new(ip, self.port));
        }
        match (host.as_str(), self.port).to_socket_addrs() {
            Ok(mut addrs) => addrs
                .next()
                .ok_or_else(|| format!("host {host:?} has no address")),
            Err(e) => Err(format!("cannot look up host {host:?}: {e}")),
        }
    }
}

/// Each `{host:N}` of `host`: (start, N, end) byte positions, end past `}`.
fn templates(host: &str) -> impl Iterator<Item = (usize, usize, usize)> + '_ {
    let mut at = 0;
    std::iter::from_fn(move || {
        let open = host[at..].find('{')? + at;
        let close = host[open..].find('}')? + open;
        at = close + 1;
        template_index(&host[open..=close]).map(|n| (open, n, close + 1))
    })
}

/// N of `{host:N}`.
fn template_index(t: &str) -> Option<usize> {
    let n = t.strip_prefix("{host:")?.strip_suffix('}')?;
    if n.is_empty() || !n.bytes().all(|b| b.is_ascii_digit()) || n.len() > 6 {
        return None;
    }
    n.parse().ok()
}

/// A DNS name: dot-separated labels of letters, digits and hyphens, none
/// empty or longer than 63, not starting or ending with a hyphen.
pub fn is_host_name(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= 253
        && s.split('.').all(|label| {
            !label.is_empty()
                && label.len() <= 63
                && !label.starts_with('-')
                && !label.ends_with('-')
                && label
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'-')
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hosts(h: &[&str]) -> Vec<String> {
        h.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn ips_names_and_templates_parse() {
        let ip = NodeAddress::parse("10.0.0.2:7400").unwrap();
        assert_eq!(
            ip.resolve(&[], "").unwrap(),
            "10.0.0.2:7400".parse().unwrap()
        );
        let v6 = NodeAddress::parse("[fd00::2]:7400").unwrap();
        assert_eq!(
            v6.resolve(&[], "").unwrap(),
            "[fd00::2]:7400".parse().unwrap()
        );
        assert!(NodeAddress::parse("node-1.cluster:7400").is_ok());
        let t = NodeAddress::parse("{host:1}-ib:7401").unwrap();
        assert_eq!(t.most_host_index(), Some(1));
        assert_eq!(t.host(&hosts(&["a", "b"]), "x").unwrap(), "b-ib");
        assert_eq!(t.port(), 7401);
    }

    #[test]
    fn bad_addresses_say_what_is_wrong() {
        for bad in [
            "7400",
            "host",
            "host:",
            "host:70000",
            "ho st:7000",
            "-host:7000",
            "::1:7000",
            "{host}:7000",
            "{host:-1}:7000",
            "{host:0:7000",
            "{rank:0}:7000",
        ] {
            let e = NodeAddress::parse(bad).unwrap_err();
            assert!(e.contains(bad), "{bad}: {e}");
        }
    }

    #[test]
    fn a_template_fills_from_the_host_list_or_says_which_is_missing() {
        let t = NodeAddress::parse("{host:0}:7400").unwrap();
        let a = t.resolve(&hosts(&["10.1.0.7"]), "launch.hosts").unwrap();
        assert_eq!(a, "10.1.0.7:7400".parse().unwrap());
        let v6 = t.resolve(&hosts(&["fd00::7"]), "launch.hosts").unwrap();
        assert_eq!(v6, "[fd00::7]:7400".parse().unwrap());
        let far = NodeAddress::parse("{host:2}:7400").unwrap();
        let e = far
            .resolve(&hosts(&["a", "b"]), "SLURM_JOB_NODELIST")
            .unwrap_err();
        assert!(e.contains("SLURM_JOB_NODELIST lists 2: a,b"), "{e}");
        let e = far.resolve(&[], "launch.hosts").unwrap_err();
        assert!(e.contains("set launch.hosts"), "{e}");
    }

    proptest::proptest! {
        /// Any text parses to an address whose filled host is an IP or a
        /// valid name, or is refused naming the text.
        #[test]
        fn any_text_parses_or_is_refused(text in "[a-z0-9.:{}\\[\\]-]{0,30}") {
            match NodeAddress::parse(&text) {
                Ok(a) => {
                    let hosts: Vec<String> = (0..8).map(|i| format!("h{i}")).collect();
                    if a.most_host_index().is_none_or(|n| n < hosts.len()) {
                        let host = a.host(&hosts, "test").unwrap();
                        proptest::prop_assert!(
                            host.parse::<IpAddr>().is_ok() || is_host_name(&host),
                            "{text:?} -> {host:?}"
                        );
                    }
                }
                Err(e) => proptest::prop_assert!(e.contains(&format!("{text:?}")), "{e}"),
            }
        }
    }

    #[test]
    fn a_name_is_looked_up() {
        let a = NodeAddress::parse("localhost:7400").unwrap();
        let got = a.resolve(&[], "").unwrap();
        assert!(got.ip().is_loopback() && got.port() == 7400, "{got}");
        let e = NodeAddress::parse("no-such-host.invalid:7400")
            .unwrap()
            .resolve(&[], "")
            .unwrap_err();
        assert!(e.contains("no-such-host.invalid"), "{e}");
    }
}
