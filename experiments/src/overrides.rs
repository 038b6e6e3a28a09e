//! A run's config: the base config file as a TOML table, with overrides
//! set by dotted key, validated by `dray_config` as a file would be.
//!
//! Every path in the table is absolute (the base config's relative paths
//! against its directory, an override's against the experiment file's),
//! so the table written out as `config.toml` means the same from any
//! directory, as `dray node` processes read it.

use crate::error::ExperimentError;
use dray_config::{is_path_key, path_keys, Config};
use std::path::Path;

/// Where an override comes from; errors name it.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Origin {
    /// The runner's own settings (output directory, no web viewer).
    Runner,
    /// `[model]`.
    Model,
    /// `[walk]`.
    Walk,
    /// `[set]`.
    Set,
    /// `[sweep]`: one value of the list.
    Sweep,
}

/// One config key set (or, with `value` None, removed).
#[derive(Clone, Debug)]
pub(crate) struct Override {
    pub origin: Origin,
    pub key: String,
    pub value: Option<toml::Value>,
}

impl Override {
    pub fn new(origin: Origin, key: &str, value: toml::Value) -> Override {
        Override {
            origin,
            key: key.to_string(),
            value: Some(value),
        }
    }

    /// An override from the experiment file: a relative path in it is
    /// taken relative to the file's directory.
    pub fn from_file(origin: Origin, key: &str, value: &toml::Value, dir: &Path) -> Override {
        let value = match value {
            toml::Value::String(s) if is_path_key(key) => path_value(&dir.join(s)),
            v => v.clone(),
        };
        Override::new(origin, key, value)
    }

    /// How errors name it, e.g. `[sweep] clients.cache_mb = 0`.
    fn label(&self) -> String {
        let value = self
            .value
            .as_ref()
            .map_or("(removed)".to_string(), |v| v.to_string());
        match self.origin {
            Origin::Runner => format!("{} (set by the runner)", self.key),
            Origin::Model => format!("[model] (sets {})", self.key),
            Origin::Walk => format!("[walk] (sets {})", self.key),
            Origin::Set => format!("[set] {}", self.key),
            Origin::Sweep => format!("[sweep] {} = {value}", self.key),
        }
    }
}

/// A path as a TOML string.
pub(crate) fn path_value(p: &Path) -> toml::Value {
    toml::Value::String(p.display().to_string())
}

/// The base config: checked as `dray sim` would load it, then held as a
/// table with absolute paths.
#[derive(Clone, Debug)]
pub(crate) struct BaseConfig {
    /// Its values, as loaded (paths resolved).
    pub config: Config,
    table: toml::Table,
}

impl BaseConfig {
    /// Loads the base config named by the experiment file `experiment`.
    pub fn load(experiment: &Path, file: &Path) -> Result<BaseConfig, ExperimentError> {
        let bad = |e: &dyn std::fmt::Display| ExperimentError::invalid(experiment, "config", e);
        let config = Config::load(file).map_err(|e| bad(&e))?;
        let text =
            std::fs::read_to_string(file).map_err(|e| bad(&format!("{}: {e}", file.display())))?;
        let mut table: toml::Table = text
            .parse()
            .map_err(|e| bad(&format!("{}: {e}", file.display())))?;
        let dir = file.parent().unwrap_or(Path::new("/"));
        for key in path_keys(config.stores.len()) {
            if let Ok(Some(toml::Value::String(p))) = get(&table, &key) {
                let absolute = path_value(&dir.join(p));
                set(&mut table, &key, Some(absolute)).map_err(|e| bad(&e))?;
            }
        }
        Ok(BaseConfig { config, table })
    }

    /// The base with `overrides` applied in order, validated. An error
    /// names the experiment file and the override that brings it: the
    /// first after which the config has this problem (the base has none).
    pub fn build(
        &self,
        experiment: &Path,
        overrides: &[Override],
    ) -> Result<(Config, toml::Table), ExperimentError> {
        let problem = match self.apply(overrides) {
            Ok(ok) => return Ok(ok),
            Err(problem) => problem,
        };
        let culprit = (1..=overrides.len())
            .find(|&k| self.apply(&overrides[..k]).err().as_ref() == Some(&problem))
            .map(|k| overrides[k - 1].label());
        let key = culprit.unwrap_or_else(|| {
            let all: Vec<String> = overrides.iter().map(Override::label).collect();
            all.join(", ")
        });
        Err(ExperimentError::invalid(experiment, key, problem))
    }

    fn apply(&self, overrides: &[Override]) -> Result<(Config, toml::Table), String> {
        let mut table = self.table.clone();
        for o in overrides {
            set(&mut table, &o.key, o.value.clone())?;
        }
        let config: Config = toml::Value::Table(table.clone())
            .try_into()
            .map_err(|e: toml::de::Error| e.message().trim().to_string())?;
        config.validate().map_err(|e| e.to_string())?;
        Ok((config, table))
    }
}

/// One step of a dotted key: `stores[1]` is `Key("stores")`, `Index(1)`.
enum Step<'a> {
    Key(&'a str),
    Index(usize),
}

fn steps(key: &str) -> Result<Vec<Step<'_>>, String> {
    let bad = || format!("{key:?} is not a dotted key (e.g. clients.count, stores[1].address)");
    let mut out = Vec::new();
    for part in key.split('.') {
        let (name, mut rest) = part.split_at(part.find('[').unwrap_or(part.len()));
        if name.is_empty() {
            return Err(bad());
        }
        out.push(Step::Key(name));
        while let Some(r) = rest.strip_prefix('[') {
            let (index, after) = r.split_once(']').ok_or_else(bad)?;
            out.push(Step::Index(index.parse().map_err(|_| bad())?));
            rest = after;
        }
        if !rest.is_empty() {
            return Err(bad());
        }
    }
    Ok(out)
}

/// Sets (or with None removes) the value at a dotted key, making missing
/// tables on the way.
pub(crate) fn set(
    table: &mut toml::Table,
    key: &str,
    value: Option<toml::Value>,
) -> Result<(), String> {
    let steps = steps(key)?;
    let mut here = toml::Value::Table(std::mem::take(table));
    let result = set_in(&mut here, &steps, value, key);
    if let toml::Value::Table(t) = here {
        *table = t;
    }
    result
}

fn set_in(
    here: &mut toml::Value,
    steps: &[Step<'_>],
    value: Option<toml::Value>,
    key: &str,
) -> Result<(), String> {
    let Some((step, rest)) = steps.split_first() else {
        return Ok(());
    };
    match (step, here) {
        (Step::Key(name), toml::Value::Table(t)) => {
            if rest.is_empty() {
                match value {
                    Some(v) => {
                        t.insert(name.to_string(), v);
                    }
                    None => {
                        t.remove(*name);
                    }
                }
                return Ok(());
            }
            if value.is_none() && !t.contains_key(*name) {
                return Ok(());
            }
            let next = t
                .entry(name.to_string())
                .or_insert_with(|| toml::Value::Table(toml::Table::new()));
            set_in(next, rest, value, key)
        }
        (Step::Index(i), toml::Value::Array(a)) => {
            let len = a.len();
            let Some(next) = a.get_mut(*i) else {
                return Err(format!(
                    "{key}: index {i} is past the end (the list has {len})"
                ));
            };
            if rest.is_empty() {
                if let Some(v) = value {
                    *next = v;
                }
                return Ok(());
            }
            set_in(next, rest, value, key)
        }
        (Step::Key(name), v) => Err(format!(
            "{key}: cannot set {name} inside a {}",
            v.type_str()
        )),
        (Step::Index(i), v) => Err(format!("{key}: cannot index [{i}] into a {}", v.type_str())),
    }
}

/// The value at a dotted key, if there is one.
pub(crate) fn get<'a>(
    table: &'a toml::Table,
    key: &str,
) -> Result<Option<&'a toml::Value>, String> {
    let mut here: Option<&toml::Value> = None;
    for step in steps(key)? {
        here = match (step, here) {
            (Step::Key(name), None) => table.get(name),
            (Step::Key(name), Some(toml::Value::Table(t))) => t.get(name),
            (Step::Index(i), Some(toml::Value::Array(a))) => a.get(i),
            _ => None,
        };
        if here.is_none() {
            return Ok(None);
        }
    }
    Ok(here)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dotted_keys() {
        let mut t: toml::Table =
            "[clients]\ncount = 1\n[[stores]]\naddress = \"a\"\n[[stores]]\naddress = \"b\"\n"
                .parse()
                .unwrap();
        set(&mut t, "clients.count", Some(toml::Value::Integer(3))).unwrap();
        set(
            &mut t,
            "stores[1].address",
            Some(toml::Value::String("c".into())),
        )
        .unwrap();
        set(
            &mut t,
            "links.client_store.latency_ms",
            Some(toml::Value::Float(5.0)),
        )
        .unwrap();
        set(&mut t, "display.web", None).unwrap();
        assert_eq!(
            get(&t, "clients.count").unwrap(),
            Some(&toml::Value::Integer(3))
        );
        assert_eq!(
            get(&t, "stores[1].address").unwrap(),
            Some(&toml::Value::String("c".into()))
        );
        assert_eq!(
            get(&t, "links.client_store.latency_ms").unwrap(),
            Some(&toml::Value::Float(5.0))
        );
        assert!(set(&mut t, "stores[5].address", Some(toml::Value::Integer(1))).is_err());
        assert!(set(&mut t, "clients.count.x", Some(toml::Value::Integer(1))).is_err());
        assert!(steps("a..b").is_err());
        assert!(steps("a[x]").is_err());
    }

    /// `path_keys` lists every path `Config::load` resolves: the table
    /// built here validates to the config the file loads to.
    #[test]
    fn the_table_means_what_the_file_meant() {
        let local = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/examples/local.toml");
        let text = std::fs::read_to_string(local)
            .unwrap()
            .replace("# camera_path = ", "camera_path = ");
        let tmp = tempfile::tempdir().unwrap();
        let file = tmp.path().join("cluster.toml");
        std::fs::write(&file, text).unwrap();
        let loaded = Config::load(&file).unwrap();
        assert!(loaded.render.camera_path.is_some());
        let base = BaseConfig::load(&tmp.path().join("x.toml"), &file).unwrap();
        let (built, _) = base.build(&tmp.path().join("x.toml"), &[]).unwrap();
        assert_eq!(built, loaded);
    }
}
