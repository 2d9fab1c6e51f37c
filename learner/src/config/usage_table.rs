//! docs/usage.md's table of every configuration key, checked against the
//! config structs: the same keys, each default as `TrainConfig::default()`
//! has it, and each preset's change as its settings have it. On a
//! mismatch the test prints the table it expects (meanings kept).

use serde::de::{self, Deserialize, Deserializer, Visitor};

use super::*;

/// Presets whose settings the table's "set by" column names (the noisy
/// presets take their group's settings, lti-blocks-N lti-paper's).
const PRESETS: [&str; 6] = ["lti-paper", "peg-group1", "peg-group2", "peg-experiment", "peg-group1-rand", "peg-group2-rand"];

/// Keys a default config does not write (an unset option, or a value
/// written only when it differs from its default): their default as the
/// table states it.
const UNWRITTEN_DEFAULTS: [(&str, &str); 5] = [
    ("base.best_constant_file", "unset"),
    ("base.residual_scale", "1.0"),
    ("ddpg.residual_scale", "unset"),
    ("run.cuda_graphs", "true"),
    ("run.eval_seed", "unset"),
];

/// A deserializer that only records the field names a struct asks for.
struct FieldNames(&'static [&'static str]);

impl<'de> Deserializer<'de> for &mut FieldNames {
    type Error = de::value::Error;

    fn deserialize_any<V: Visitor<'de>>(self, _visitor: V) -> Result<V::Value, Self::Error> {
        Err(de::Error::custom("not a struct"))
    }

    fn deserialize_struct<V: Visitor<'de>>(self, _name: &'static str, fields: &'static [&'static str], _visitor: V) -> Result<V::Value, Self::Error> {
        self.0 = fields;
        Err(de::Error::custom("names recorded"))
    }

    serde::forward_to_deserialize_any! {
        bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf option unit
        unit_struct newtype_struct seq tuple tuple_struct map enum identifier ignored_any
    }
}

fn fields<'de, T: Deserialize<'de>>() -> &'static [&'static str] {
    let mut names = FieldNames(&[]);
    let _ = T::deserialize(&mut names);
    names.0
}

/// Every `section.key`, in the structs' order.
fn every_key() -> Vec<(String, String)> {
    let sections: [(&str, &[&str]); 5] = [
        ("network", fields::<NetworkConfig>()),
        ("ddpg", fields::<DdpgConfig>()),
        ("ppo", fields::<PpoConfig>()),
        ("run", fields::<RunConfig>()),
        ("base", fields::<BaseConfig>()),
    ];
    sections.iter().flat_map(|(section, keys)| keys.iter().map(|key| (section.to_string(), key.to_string()))).collect()
}

/// A value as a TOML file spells it (arrays on one line).
fn spelled(value: Option<&toml::Value>) -> Option<String> {
    value.map(|v| match v {
        toml::Value::Array(items) => format!("[{}]", items.iter().map(|i| spelled(Some(i)).unwrap_or_default()).collect::<Vec<_>>().join(", ")),
        other => other.to_string(),
    })
}

fn value_of(cfg: &TrainConfig, section: &str, key: &str) -> Option<String> {
    let table = toml::Table::try_from(cfg).expect("a config serializes");
    spelled(table.get(section).and_then(|s| s.get(key)))
}

/// One row as the test expects it: section, key, default, set by.
fn expected_row(section: &str, key: &str) -> [String; 4] {
    let default = TrainConfig::default();
    let name = format!("{section}.{key}");
    let default_value = value_of(&default, section, key)
        .or_else(|| UNWRITTEN_DEFAULTS.iter().find(|(k, _)| *k == name).map(|(_, v)| v.to_string()))
        .unwrap_or_else(|| panic!("{name} is not written by a default config: add its default to UNWRITTEN_DEFAULTS"));
    let default_written = value_of(&default, section, key);
    // Presets with the same value share one entry: "0.5 (peg-group1, peg-group2)".
    let mut changes: Vec<(String, Vec<&str>)> = Vec::new();
    for preset in PRESETS {
        let value = value_of(&TrainConfig::for_env(preset).0, section, key);
        if value == default_written {
            continue;
        }
        let value = value.unwrap_or_else(|| "unset".into());
        match changes.iter_mut().find(|(v, _)| *v == value) {
            Some((_, presets)) => presets.push(preset),
            None => changes.push((value, vec![preset])),
        }
    }
    let named = |presets: &[&str]| {
        let pegs: Vec<&str> = PRESETS.iter().copied().filter(|p| p.starts_with("peg-")).collect();
        let mut names: Vec<&str> = presets.iter().copied().filter(|p| !pegs.contains(p)).collect();
        match pegs.iter().all(|p| presets.contains(p)) {
            true => names.push("every peg preset"),
            false => names.extend(presets.iter().copied().filter(|p| pegs.contains(p))),
        }
        names.join(", ")
    };
    let set_by = changes.iter().map(|(v, presets)| format!("`{v}` ({})", named(presets))).collect::<Vec<_>>().join("; ");
    let set_by = if set_by.is_empty() { "—".to_string() } else { set_by };
    [section.to_string(), format!("`{key}`"), format!("`{default_value}`"), set_by]
}

/// The table's rows in docs/usage.md: its cells, trimmed.
fn documented_rows() -> Vec<Vec<String>> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/usage.md");
    let text = std::fs::read_to_string(path).expect("docs/usage.md");
    // No table: none of its rows (the test then prints the whole table).
    let Some(start) = text.find("| section | key |") else { return Vec::new() };
    text[start..]
        .lines()
        .skip(2)
        .take_while(|line| line.starts_with('|'))
        .map(|line| line.trim_matches('|').split(" | ").map(|cell| cell.trim().to_string()).collect())
        .collect()
}

#[test]
fn the_usage_table_lists_every_key_with_its_default_and_presets() {
    let documented = documented_rows();
    let mut expected = Vec::new();
    for (section, key) in every_key() {
        let [s, k, d, p] = expected_row(&section, &key);
        let meaning = documented.iter().find(|row| row.len() == 5 && row[0] == s && row[1] == k).map_or(String::new(), |row| row[4].clone());
        expected.push(vec![s, k, d, p, meaning]);
    }
    let table = expected.iter().map(|row| format!("| {} |", row.join(" | "))).collect::<Vec<_>>().join("\n");
    assert_eq!(documented, expected, "docs/usage.md's configuration table should read:\n| section | key | default | set by presets | meaning |\n|---|---|---|---|---|\n{table}\n");
    for row in &documented {
        assert!(!row[4].is_empty(), "{}.{} has no meaning in docs/usage.md", row[0], row[1]);
    }
}
