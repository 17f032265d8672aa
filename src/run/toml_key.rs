//! Where in a TOML text a deserialisation error points: its line and the dotted key path, so a
//! refused configuration names the key to change (`motion.mediastinum`) and not only serde's
//! message ("unknown variant `glue`").

/// The 1-based line and the dotted key path (`table.key`) of `error` in `text`, when the
/// error carries a position.
fn locate(text: &str, error: &toml::de::Error) -> Option<(usize, Option<String>)> {
    // `get` rather than slicing: a span that is not on a character boundary gives no
    // location instead of a panic inside an error path.
    let before = text.get(..error.span()?.start.min(text.len()))?;
    let line_index = before.matches('\n').count();
    let lines: Vec<&str> = text.lines().collect();
    let line = lines.get(line_index).copied().unwrap_or("");
    let key = key_of_line(line).map(|key| {
        let table = lines[..line_index.min(lines.len())]
            .iter()
            .rev()
            .find_map(|l| table_header(l));
        match table {
            Some(t) => format!("{t}.{key}"),
            None => key.to_string(),
        }
    });
    // A header line itself (`[motoin]`): the table is the key.
    let key = key.or_else(|| table_header(line).map(str::to_string));
    Some((line_index + 1, key))
}

/// The dotted key `error` points at in `text`, if any, and its message with the line appended
/// (`unknown variant `glue`, expected … (line 5)`): what a refused configuration reports.
pub fn describe(text: &str, error: &toml::de::Error) -> (Option<String>, String) {
    let message = error.message().trim();
    match locate(text, error) {
        Some((line, key)) => (key, format!("{message} (line {line})")),
        None => (None, message.to_string()),
    }
}

/// `key` of a `key = value` line (quotes and spaces trimmed); `None` for other lines.
fn key_of_line(line: &str) -> Option<&str> {
    let line = line.trim_start();
    if line.starts_with('[') || line.starts_with('#') {
        return None;
    }
    let (key, _) = line.split_once('=')?;
    let key = key.trim().trim_matches('"').trim_matches('\'');
    (!key.is_empty()).then_some(key)
}

/// `table` of a `[table]` or `[[table]]` header line.
fn table_header(line: &str) -> Option<&str> {
    let line = line.split('#').next()?.trim();
    let inner = line.strip_prefix('[')?.strip_suffix(']')?;
    let inner = inner.trim_start_matches('[').trim_end_matches(']').trim();
    (!inner.is_empty()).then_some(inner)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Doc {
        size: Option<f64>,
        motion: Option<Motion>,
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Motion {
        mediastinum: Option<Kind>,
        share: Option<f64>,
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(rename_all = "snake_case")]
    enum Kind {
        Sliding,
    }

    fn located(text: &str) -> (usize, Option<String>) {
        let e = toml::from_str::<Doc>(text).unwrap_err();
        locate(text, &e).unwrap()
    }

    #[test]
    fn names_the_line_and_the_dotted_key() {
        let text = "size = 6.0\n\n[motion] # the breath\nshare = 0.3\nmediastinum = \"glue\"\n";
        assert_eq!(located(text), (5, Some("motion.mediastinum".into())));
        assert_eq!(located("size = \"six\"\n"), (1, Some("size".into())));
        let unknown = located("[motion]\nshere = 0.3\n");
        assert_eq!(unknown, (2, Some("motion.shere".into())));
        assert_eq!(located("[motoin]\n"), (1, Some("motoin".into())));
        let text = "[motion]\nmediastinum = \"glue\"\n";
        let (key, reason) = describe(text, &toml::from_str::<Doc>(text).unwrap_err());
        assert_eq!(key.as_deref(), Some("motion.mediastinum"));
        assert!(
            reason.contains("glue") && reason.ends_with(" (line 2)"),
            "{reason}"
        );
    }
}
