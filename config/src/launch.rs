//! Which node a process is when a launcher started it: `dray node --config
//! C` without `--role` reads its rank from the environment that Slurm, an
//! MPI launcher or Kubernetes gives each process, and the config's
//! `launch.ranks` (by default every node in [`crate::Config::node_names`]
//! order) says which node each rank runs. Slurm also gives the list of
//! hosts that `{host:N}` addresses name.

use std::collections::HashSet;

/// The variables read, in the order they are tried: an MPI launcher's rank
/// first, because `mpirun` inside a Slurm job leaves every rank the batch
/// step's `SLURM_PROCID` of 0.
const RANK_SOURCES: [(&str, &str, Option<&str>); 5] = [
    (
        "Open MPI",
        "OMPI_COMM_WORLD_RANK",
        Some("OMPI_COMM_WORLD_SIZE"),
    ),
    ("PMIx", "PMIX_RANK", None),
    ("an MPI launcher (PMI)", "PMI_RANK", Some("PMI_SIZE")),
    ("Slurm", "SLURM_PROCID", Some("SLURM_NTASKS")),
    ("a Kubernetes Indexed Job", "JOB_COMPLETION_INDEX", None),
];

/// Slurm's node lists, the step's first.
const HOST_LISTS: [&str; 3] = [
    "SLURM_STEP_NODELIST",
    "SLURM_JOB_NODELIST",
    "SLURM_NODELIST",
];

/// What the launcher told this process.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Launch {
    /// Who started it, in words (e.g. "Slurm").
    pub launcher: &'static str,
    /// The variable the rank came from (e.g. `SLURM_PROCID`).
    pub rank_from: &'static str,
    /// This process's rank, from 0.
    pub rank: usize,
    /// How many processes the launcher started, where it says:
    /// (variable, count).
    pub size: Option<(&'static str, usize)>,
}

/// The rank from the first launcher whose variable is set; None when no
/// launcher's is (a Kubernetes StatefulSet's ordinal counts only inside
/// Kubernetes, where `KUBERNETES_SERVICE_HOST` is set).
pub fn detect(env: &dyn Fn(&str) -> Option<String>) -> Result<Option<Launch>, String> {
    let number = |var: &str, text: &str| {
        text.trim()
            .parse::<usize>()
            .map_err(|_| format!("{var}={text:?} is not a whole number"))
    };
    for (launcher, rank_var, size_var) in RANK_SOURCES {
        let Some(text) = env(rank_var) else { continue };
        let rank = number(rank_var, &text)?;
        let size = match size_var.and_then(|v| env(v).map(|t| (v, t))) {
            Some((v, t)) => Some((v, number(v, &t)?)),
            None => None,
        };
        if let Some((v, n)) = size.filter(|&(_, n)| rank >= n) {
            return Err(format!(
                "{rank_var}={rank} is not below {v}={n}: the launcher's environment is inconsistent"
            ));
        }
        return Ok(Some(Launch {
            launcher,
            rank_from: rank_var,
            rank,
            size,
        }));
    }
    if env("KUBERNETES_SERVICE_HOST").is_some() {
        if let Some(host) = env("HOSTNAME") {
            // A StatefulSet's pod is named NAME-ORDINAL.
            if let Some(ordinal) = host.rsplit_once('-').and_then(|(_, n)| n.parse().ok()) {
                return Ok(Some(Launch {
                    launcher: "a Kubernetes StatefulSet",
                    rank_from: "HOSTNAME",
                    rank: ordinal,
                    size: None,
                }));
            }
        }
    }
    Ok(None)
}

/// The launcher's host list, expanded, and the variable it came from.
pub fn hosts(
    env: &dyn Fn(&str) -> Option<String>,
) -> Result<Option<(&'static str, Vec<String>)>, String> {
    for var in HOST_LISTS {
        if let Some(text) = env(var).filter(|t| !t.trim().is_empty()) {
            let list = expand_host_list(text.trim()).map_err(|e| format!("{var}={text:?}: {e}"))?;
            return Ok(Some((var, list)));
        }
    }
    Ok(None)
}

/// What a process should say when nothing tells it its role.
pub const NO_LAUNCHER: &str = "no --role given and no launcher's rank in the environment: \
    give --role (and --index), or start the node with Slurm (SLURM_PROCID), an MPI launcher \
    (OMPI_COMM_WORLD_RANK, PMIX_RANK or PMI_RANK) or Kubernetes (JOB_COMPLETION_INDEX, or a \
    StatefulSet pod's host name)";

/// Most hosts one list may expand to.
const MAX_HOSTS: usize = 1 << 16;

/// Expands a Slurm host list: names separated by commas, where `[a-b,c]`
/// ranges keep the width of their first number (`node[08-10],gpu1` is
/// node08, node09, node10, gpu1); several brackets in one name multiply.
pub fn expand_host_list(list: &str) -> Result<Vec<String>, String> {
    let mut out = Vec::new();
    // Split at commas outside brackets.
    let mut depth = 0i32;
    let mut start = 0;
    let mut items = Vec::new();
    for (i, c) in list.char_indices() {
        match c {
            '[' => depth += 1,
            ']' => depth -= 1,
            ',' if depth == 0 => {
                items.push(&list[start..i]);
                start = i + 1;
            }
            _ => {}
        }
        if !(0..=1).contains(&depth) {
            return Err("brackets do not pair".into());
        }
    }
    if depth != 0 {
        return Err("brackets do not pair".into());
    }
    items.push(&list[start..]);
    for item in items {
        if item.is_empty() {
            return Err("an empty host name".into());
        }
        let mut names = vec![String::new()];
        let mut rest = item;
        while let Some(open) = rest.find('[') {
            let close = rest.find(']').ok_or("brackets do not pair")?;
            let prefix = &rest[..open];
            let numbers = ranges(&rest[open + 1..close])?;
            if names.len().saturating_mul(numbers.len()) > MAX_HOSTS {
                return Err(format!("more than {MAX_HOSTS} hosts"));
            }
            names = names
                .iter()
                .flat_map(|n| numbers.iter().map(move |x| format!("{n}{prefix}{x}")))
                .collect();
            rest = &rest[close + 1..];
        }
        if rest.contains(']') {
            return Err("brackets do not pair".into());
        }
        for n in names {
            let name = n + rest;
            if !crate::address::is_host_name(&name) {
                return Err(format!("{name:?} is not a host name"));
            }
            out.push(name);
        }
        if out.len() > MAX_HOSTS {
            return Err(format!("more than {MAX_HOSTS} hosts"));
        }
    }
    Ok(out)
}

/// `08-10,12` as zero-padded numbers.
fn ranges(text: &str) -> Result<Vec<String>, String> {
    let mut out = Vec::new();
    for part in text.split(',') {
        let bad = || format!("{part:?} is not a number or a range A-B");
        let (a, b) = part.split_once('-').unwrap_or((part, part));
        if a.is_empty() || !a.bytes().all(|c| c.is_ascii_digit()) || b.is_empty() {
            return Err(bad());
        }
        let (lo, hi): (u64, u64) = (a.parse().map_err(|_| bad())?, b.parse().map_err(|_| bad())?);
        if hi < lo || hi - lo >= MAX_HOSTS as u64 || out.len() + (hi - lo) as usize >= MAX_HOSTS {
            return Err(bad());
        }
        let width = a.len();
        out.extend((lo..=hi).map(|x| format!("{x:0width$}")));
    }
    Ok(out)
}

/// Checks `launch.ranks`: node names of the config, each once.
pub(crate) fn check_ranks(ranks: &[String], nodes: &[String]) -> Result<(), String> {
    let mut seen = HashSet::new();
    for (r, name) in ranks.iter().enumerate() {
        if !nodes.contains(name) {
            let last = |role: &str| {
                nodes
                    .iter()
                    .rfind(|n| n.starts_with(role))
                    .map_or(String::new(), |n| format!(", {role}0 to {n}"))
            };
            return Err(format!(
                "rank {r}: {name:?} is not a node of this config (scheduler, display{}{})",
                last("store-"),
                last("client-")
            ));
        }
        if !seen.insert(name) {
            return Err(format!("rank {r}: {name} has another rank too"));
        }
    }
    if ranks.is_empty() {
        return Err("no ranks".into());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn env(vars: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
        let m: HashMap<String, String> = vars
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        move |k| m.get(k).cloned()
    }

    #[test]
    fn slurm_gives_the_rank_the_task_count_and_the_hosts() {
        let e = env(&[
            ("SLURM_PROCID", "3"),
            ("SLURM_NTASKS", "6"),
            ("SLURM_JOB_NODELIST", "n[1-9]"),
            ("SLURM_STEP_NODELIST", "node[08-10],gpu1"),
        ]);
        let l = detect(&e).unwrap().unwrap();
        assert_eq!(
            (l.launcher, l.rank, l.size),
            ("Slurm", 3, Some(("SLURM_NTASKS", 6)))
        );
        let (from, h) = hosts(&e).unwrap().unwrap();
        assert_eq!(from, "SLURM_STEP_NODELIST");
        assert_eq!(h, ["node08", "node09", "node10", "gpu1"]);
    }

    #[test]
    fn an_mpi_rank_wins_over_the_batch_steps_slurm_procid() {
        let ompi = env(&[
            ("SLURM_PROCID", "0"),
            ("OMPI_COMM_WORLD_RANK", "4"),
            ("OMPI_COMM_WORLD_SIZE", "5"),
        ]);
        let l = detect(&ompi).unwrap().unwrap();
        assert_eq!((l.launcher, l.rank), ("Open MPI", 4));
        let pmi = detect(&env(&[("PMI_RANK", "2"), ("PMI_SIZE", "3")]))
            .unwrap()
            .unwrap();
        assert_eq!(
            (pmi.rank_from, pmi.rank, pmi.size),
            ("PMI_RANK", 2, Some(("PMI_SIZE", 3)))
        );
        let pmix = detect(&env(&[("PMIX_RANK", "7")])).unwrap().unwrap();
        assert_eq!((pmix.rank, pmix.size), (7, None));
    }

    #[test]
    fn kubernetes_gives_the_job_index_or_the_statefulset_ordinal() {
        let job = detect(&env(&[("JOB_COMPLETION_INDEX", "5")]))
            .unwrap()
            .unwrap();
        assert_eq!((job.launcher, job.rank), ("a Kubernetes Indexed Job", 5));
        let sts = env(&[
            ("KUBERNETES_SERVICE_HOST", "10.96.0.1"),
            ("HOSTNAME", "dray-12"),
        ]);
        assert_eq!(detect(&sts).unwrap().unwrap().rank, 12);
        // Outside Kubernetes a host name ending in a number means nothing.
        assert_eq!(detect(&env(&[("HOSTNAME", "dray-12")])).unwrap(), None);
        let odd = env(&[("KUBERNETES_SERVICE_HOST", "x"), ("HOSTNAME", "dray")]);
        assert_eq!(detect(&odd).unwrap(), None);
    }

    #[test]
    fn a_bad_rank_names_the_variable() {
        let e = detect(&env(&[("SLURM_PROCID", "x")])).unwrap_err();
        assert!(e.contains("SLURM_PROCID=\"x\""), "{e}");
        let e = detect(&env(&[("SLURM_PROCID", "6"), ("SLURM_NTASKS", "6")])).unwrap_err();
        assert!(e.contains("SLURM_NTASKS=6"), "{e}");
        assert_eq!(detect(&env(&[])).unwrap(), None);
    }

    #[test]
    fn host_lists_expand_like_slurms() {
        assert_eq!(expand_host_list("a").unwrap(), ["a"]);
        assert_eq!(
            expand_host_list("rack[1-2]-n[01,3]").unwrap(),
            ["rack1-n01", "rack1-n3", "rack2-n01", "rack2-n3"]
        );
        assert_eq!(expand_host_list("n[9-11]").unwrap(), ["n9", "n10", "n11"]);
        for bad in [
            "",
            "n[1-",
            "n]1[",
            "n[2-1]",
            "n[a]",
            "n[1-2],,m",
            "n[1-99999999]",
            "bad_name",
        ] {
            assert!(expand_host_list(bad).is_err(), "{bad}");
        }
    }

    proptest::proptest! {
        /// Any text, as a hostile or confused launcher might set it, gives
        /// a list of valid host names of bounded length or an error.
        #[test]
        fn any_host_list_expands_or_is_refused(text in "[a-z0-9\\[\\],.-]{0,40}") {
            if let Ok(hosts) = expand_host_list(&text) {
                proptest::prop_assert!(hosts.len() <= MAX_HOSTS);
                for h in hosts {
                    proptest::prop_assert!(crate::address::is_host_name(&h), "{h:?}");
                }
            }
        }

        /// A list of names with ranges expands to every name in order.
        #[test]
        fn ranges_expand_in_order(lo in 0u32..500, n in 1u32..20, width in 1usize..5) {
            let hi = lo + n - 1;
            let list = format!("n[{lo:0width$}-{hi}],x");
            let hosts = expand_host_list(&list).unwrap();
            proptest::prop_assert_eq!(hosts.len() as u32, n + 1);
            for (k, h) in hosts[..n as usize].iter().enumerate() {
                proptest::prop_assert_eq!(h, &format!("n{:0width$}", lo + k as u32));
            }
        }
    }

    #[test]
    fn ranks_name_each_node_once() {
        let nodes: Vec<String> = ["scheduler", "display", "store-0", "client-0"]
            .map(String::from)
            .to_vec();
        assert!(check_ranks(&nodes, &nodes).is_ok());
        let e = check_ranks(&["client-1".into()], &nodes).unwrap_err();
        assert!(e.contains("\"client-1\" is not a node"), "{e}");
        let e = check_ranks(&["display".into(), "display".into()], &nodes).unwrap_err();
        assert!(e.contains("rank 1: display"), "{e}");
    }
}
