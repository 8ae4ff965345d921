//! From TOML text to a checked [`Scene`]: serde's errors given their line and dotted key, a
//! failed check the line of the key it names.

use super::spec::Scene;
use crate::error::{Error, Result};
use std::path::{Path, PathBuf};

impl Scene {
    /// Reads and validates a scene file.
    pub fn from_file(path: &Path) -> Result<Scene> {
        let text = crate::math::input::read_text(path)
            .map_err(|source| Error::ReadScene { path: path.to_path_buf(), source })?;
        let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
        Scene::from_toml_in(&text, &path.display().to_string(), base)
    }

    /// Parses and validates TOML text whose relative mesh paths start from `base`.
    pub fn from_toml_in(text: &str, origin: &str, base: PathBuf) -> Result<Scene> {
        let mut scene = Scene::parse(text, origin)?;
        scene.base_dir = Some(base);
        scene.validated(text, origin)
    }

    /// Parses and validates a scene from TOML text; `origin` names it in errors. Relative
    /// mesh paths start from the current folder (use [`Scene::from_toml_in`] to give another).
    pub fn from_toml(text: &str, origin: &str) -> Result<Scene> {
        Scene::from_toml_in(text, origin, PathBuf::from("."))
    }

    fn parse(text: &str, origin: &str) -> Result<Scene> {
        toml::from_str(text).map_err(|e| {
            let msg = e.message().trim().replace('\n', " ");
            // A field the whole file lacks (span 0..0): no line to point at (it said
            // `line 1: name: missing field `fluid``, naming whatever came first).
            if e.span() == Some(0..0) {
                if let Some(field) =
                    msg.strip_prefix("missing field `").and_then(|m| m.strip_suffix('`'))
                {
                    let what = if ["domain", "time", "fluid"].contains(&field) {
                        format!("the [{field}] table is missing")
                    } else {
                        format!("the key `{field}` is missing (at the top, before any table)")
                    };
                    return Error::ParseScene { origin: origin.to_string(), message: what };
                }
            }
            let line = e.span().map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
            Error::ParseScene {
                origin: origin.to_string(),
                message: match line {
                    Some(l) => {
                        // Name the table when the error points at its header ("missing field").
                        let header = text.lines().nth(l - 1).map(str::trim).unwrap_or("");
                        if header.starts_with('[') && header.ends_with(']') {
                            format!("line {l}: in {header}: {msg}")
                        } else if let Some(key) = dotted_key(text, l) {
                            format!("line {l}: {key}: {msg}")
                        } else {
                            format!("line {l}: {msg}")
                        }
                    }
                    None => msg,
                },
            }
        })
    }

    fn validated(self, text: &str, origin: &str) -> Result<Scene> {
        self.validate().map_err(|p| {
            let at = locate(text, &p.key).map(|l| format!("line {l}: ")).unwrap_or_default();
            Error::InvalidScene {
                origin: origin.to_string(),
                message: format!("{at}{}: {}", p.key, p.message),
            }
        })?;
        Ok(self)
    }
}

/// The 1-based line of `path` (`"domain.dx"`, `"liquid[1]"`, `"solver"`) in a TOML text, when
/// the file is laid out with one table header per section, as the shipped scenes are.
fn locate(src: &str, path: &str) -> Option<usize> {
    let mut parts = path.split('.');
    let head = parts.next()?;
    let key = parts.next();
    let (table, nth) = match head.split_once('[') {
        Some((t, rest)) => (t, rest.trim_end_matches(']').parse::<usize>().ok()?),
        None => (head, 0),
    };
    let headers = [format!("[{table}]"), format!("[[{table}]]")];
    let mut seen = 0usize;
    let mut start = None;
    for (n, line) in src.lines().enumerate() {
        let t = line.trim();
        if headers.iter().any(|h| t == h) {
            if seen == nth {
                start = Some(n);
                break;
            }
            seen += 1;
        }
    }
    let start = match start {
        Some(s) => s,
        // A top-level key, or a dotted key without its own header.
        None => {
            return src
                .lines()
                .position(|l| {
                    let t = l.trim_start();
                    t.starts_with(head) && t[head.len()..].trim_start().starts_with('=')
                })
                .map(|n| n + 1)
        }
    };
    let Some(key) = key else {
        return Some(start + 1);
    };
    for (n, line) in src.lines().enumerate().skip(start + 1) {
        let t = line.trim_start();
        if t.starts_with('[') {
            break;
        }
        if t.starts_with(key) && t[key.len()..].trim_start().starts_with('=') {
            return Some(n + 1);
        }
    }
    Some(start + 1)
}

/// `table.key` of a `key = value` line `l` (1-based) under a `[table]` or `[[table]]`
/// header (`key` alone at the top level).
fn dotted_key(src: &str, l: usize) -> Option<String> {
    let lines: Vec<&str> = src.lines().collect();
    let line = lines.get(l - 1)?;
    if line.trim_start().starts_with('#') {
        return None;
    }
    let key = line.split_once('=')?.0.trim();
    if key.is_empty() || key.contains(['[', '{', '"']) {
        return None;
    }
    let table = lines[..l - 1]
        .iter()
        .rev()
        .map(|s| s.trim())
        .find(|s| s.starts_with('[') && s.ends_with(']'))
        .map(|h| h.trim_matches(|c| c == '[' || c == ']'));
    Some(match table {
        Some(t) => format!("{t}.{key}"),
        None => key.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn locate_finds_keys_in_tables() {
        let src = "name = \"x\"\n[domain]\nsize = [1, 1, 1]\ndx = 0.1\n[[liquid]]\na = 1\n[[liquid]]\nb = 2\n";
        assert_eq!(locate(src, "domain.dx"), Some(4));
        assert_eq!(locate(src, "liquid[1]"), Some(7));
        assert_eq!(locate(src, "name"), Some(1));
    }
}
