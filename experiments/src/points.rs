//! The sweep: every combination of the swept values is a point.

/// One combination of swept values, in the sweep's key order.
#[derive(Clone, Debug, PartialEq)]
pub struct Point {
    /// Its place in the sweep, from 0; names its runs' directories.
    pub index: usize,
    /// Swept key and value.
    pub values: Vec<(String, toml::Value)>,
}

impl Point {
    /// The values as CSV cells, in key order.
    pub fn cells(&self) -> Vec<String> {
        self.values.iter().map(|(_, v)| cell(v)).collect()
    }

    /// For people: `clients.miss_mode=block links.client_store.latency_ms=5`
    /// (`(no sweep)` for the single point of an experiment without one).
    pub fn label(&self) -> String {
        if self.values.is_empty() {
            return "(no sweep)".into();
        }
        let parts: Vec<String> = self
            .values
            .iter()
            .map(|(k, v)| format!("{k}={}", cell(v)))
            .collect();
        parts.join(" ")
    }

    /// The directory of one of its runs, under `runs/`.
    pub fn run_dir_name(&self, repeat: u32) -> String {
        format!("p{:03}-r{repeat}", self.index)
    }
}

/// A value as a CSV cell: a labelled value's label, a string bare,
/// anything else as TOML writes it.
pub fn cell(v: &toml::Value) -> String {
    match labelled(v) {
        Some((label, _)) => cell(label),
        None => match v {
            toml::Value::String(s) => s.clone(),
            other => other.to_string(),
        },
    }
}

/// A swept value written `{ label = L, value = V }`: `L` names it in the
/// CSV files, the summary and the plots, `V` is what the config gets
/// (for values too long to read, such as a list of stores).
pub fn labelled(v: &toml::Value) -> Option<(&toml::Value, &toml::Value)> {
    let t = v.as_table()?;
    match (t.len(), t.get("label"), t.get("value")) {
        (2, Some(label), Some(value)) => Some((label, value)),
        _ => None,
    }
}

/// What the config gets of a swept value: the value of a labelled one.
pub fn config_value(v: &toml::Value) -> &toml::Value {
    labelled(v).map_or(v, |(_, value)| value)
}

/// Every combination of the lists, the first key varying slowest; one
/// point with no values when nothing is swept.
pub fn points(sweep: &[(String, Vec<toml::Value>)]) -> Vec<Point> {
    let mut combos: Vec<Vec<(String, toml::Value)>> = vec![Vec::new()];
    for (key, values) in sweep {
        combos = combos
            .into_iter()
            .flat_map(|combo| {
                values.iter().map(move |v| {
                    let mut next = combo.clone();
                    next.push((key.clone(), v.clone()));
                    next
                })
            })
            .collect();
    }
    combos
        .into_iter()
        .enumerate()
        .map(|(index, values)| Point { index, values })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use toml::Value;

    #[test]
    fn every_combination() {
        let sweep = vec![
            ("a".to_string(), vec![Value::Integer(0), Value::Integer(5)]),
            (
                "b".to_string(),
                vec![
                    Value::String("x".into()),
                    Value::String("y".into()),
                    Value::Boolean(true),
                ],
            ),
        ];
        let p = points(&sweep);
        assert_eq!(p.len(), 6);
        assert_eq!(p[0].cells(), ["0", "x"]);
        assert_eq!(p[2].cells(), ["0", "true"]);
        assert_eq!(p[5].label(), "a=5 b=true");
        assert_eq!(p[5].run_dir_name(2), "p005-r2");
        assert_eq!(points(&[]).len(), 1);
        assert_eq!(points(&[])[0].label(), "(no sweep)");
    }

    #[test]
    fn a_labelled_value_shows_its_label_and_gives_the_config_its_value() {
        let v: Value = toml::from_str::<toml::Table>(
            r#"x = { label = 2, value = [{ address = "a" }, { address = "b" }] }"#,
        )
        .unwrap()["x"]
            .clone();
        assert_eq!(cell(&v), "2");
        assert_eq!(config_value(&v).as_array().map(Vec::len), Some(2));
        assert_eq!(crate::spec::number(&v), Some(2.0));
        // A table with other keys is a plain value.
        let plain: Value =
            toml::from_str::<toml::Table>(r#"x = { label = 2, other = 1 }"#).unwrap()["x"].clone();
        assert!(labelled(&plain).is_none());
        assert_eq!(config_value(&plain), &plain);
    }
}
