//! How input errors read: the TOML parser's and serde's messages ("invalid
//! type: floating point `0.5`, expected an array of length 2", "wanted
//! exactly 1 element") put in the words of the file's author, with the key
//! they concern, the closest valid key or choice for a typo, and user
//! values shortened (a 20 MB value is never echoed whole).

/// Longest user value or line of a file echoed in a message, in characters.
pub const ECHO: usize = 80;

/// The choice nearest to `got` by edit distance, when it is near enough to
/// be a typo.
pub fn closest<'a>(got: &str, choices: &[&'a str]) -> Option<&'a str> {
    choices.iter().map(|c| (strsim::damerau_levenshtein(got, c), *c)).filter(|(d, c)| *d <= 2.max(c.len() / 3)).min_by_key(|(d, _)| *d).map(|(_, c)| c)
}

/// "unknown X `y`; did you mean `z`?" (or the list of choices).
pub fn unknown(what: &str, got: &str, choices: &[&str]) -> String {
    let shown = crate::files::shorten(got, ECHO);
    match closest(got, choices) {
        Some(best) => format!("unknown {what} `{shown}`; did you mean `{best}`?"),
        None => format!("unknown {what} `{shown}`; expected one of {}", choices.join(", ")),
    }
}

/// A parser's message in plain words. Returns the key path the message
/// ends with (serde's "in `key`" when the value was deserialised from a
/// part of the file) and the message; the source lines quoted by the TOML
/// parser are kept, shortened.
pub fn plain(message: &str) -> (Option<String>, String) {
    let message = message.trim();
    let (body, key) = match message.rsplit_once("\nin `") {
        Some((body, key)) if key.ends_with('`') && !key[..key.len() - 1].contains('\n') => (body, Some(key[..key.len() - 1].to_string())),
        _ => (message, None),
    };
    let lines: Vec<String> = body
        .lines()
        .map(|line| {
            // The parser's quotes of the file: "10 | text" and "   |   ^".
            let quoted = line.split_once('|').is_some_and(|(head, _)| head.trim().chars().all(|c| c.is_ascii_digit()));
            if quoted || line.starts_with("TOML parse error") { crate::files::shorten(line, 2 * ECHO) } else { reason(line) }
        })
        .collect();
    (key, lines.join("\n"))
}

/// [`plain`] with the key, if any, put in front: "`key`: message".
pub fn plain_with_key(message: &str) -> String {
    match plain(message) {
        (Some(key), text) => format!("`{key}`: {text}"),
        (None, text) => text,
    }
}

/// One line of a serde message in plain words.
fn reason(line: &str) -> String {
    let m = line.trim();
    for prefix in ["invalid type: ", "invalid value: "] {
        if let Some((got, want)) = m.strip_prefix(prefix).and_then(|rest| rest.rsplit_once(", expected ")) {
            return format!("expected {}, got {}", expected(want), given(got));
        }
    }
    if let Some((n, want)) = m.strip_prefix("invalid length ").and_then(|rest| rest.split_once(", expected ")) {
        return format!("expected {}, got {n} value(s)", expected(want));
    }
    if m.starts_with("wanted exactly 1 element") {
        let got = if m.contains("more than") { "several" } else { "none" };
        return format!("expected exactly one kind, written as a table with one key (e.g. `{{ box = {{ … }} }}`), got {got}");
    }
    if let Some(rest) = m.strip_prefix("unknown field `").or_else(|| m.strip_prefix("unknown variant `")) {
        let what = if m.starts_with("unknown field") { "key" } else { "kind" };
        // The name given may hold backticks itself: the choices follow the
        // last "`, expected".
        if let Some((got, tail)) = rest.rsplit_once("`, expected").or_else(|| rest.split_once('`')) {
            let choices: Vec<&str> = tail.split('`').skip(1).step_by(2).collect();
            return if choices.is_empty() { format!("unknown {what} `{}`", crate::files::shorten(got, ECHO)) } else { unknown(what, got, &choices) };
        }
    }
    if let Some(rest) = m.strip_prefix("missing field `") {
        return format!("missing key `{}`", rest.trim_end_matches('`'));
    }
    if m.starts_with("data did not match any variant of untagged enum") {
        return "the value has none of the accepted forms (see the documentation of this key)".into();
    }
    crate::files::shorten(m, 2 * ECHO)
}

/// What serde expected, in plain words.
fn expected(want: &str) -> String {
    let want = want.trim();
    match want {
        "f64" | "f32" | "a float" => "a number".into(),
        "i64" | "i32" | "u64" | "u32" | "usize" | "u8" | "u16" | "an integer" => "a whole number".into(),
        "a sequence" | "a vec" => "a list".into(),
        "a map" => "a table".into(),
        "a string" | "a boolean" | "a borrowed string" => want.into(),
        _ => {
            if let Some(n) = want.strip_prefix("an array of length ") {
                format!("a list of {n} values")
            } else if want.starts_with("struct ") {
                "a table".into()
            } else if want.starts_with("enum ") || want.starts_with("string or map") {
                "a kind (a string, or a table with one key)".into()
            } else {
                crate::files::shorten(want, ECHO)
            }
        }
    }
}

/// The value serde got, in plain words and shortened.
fn given(got: &str) -> String {
    let got = got.trim();
    let quoted = |s: &str| s.split_once('`').and_then(|(_, r)| r.rsplit_once('`')).map(|(v, _)| crate::files::shorten(v, ECHO));
    if let Some(s) = got.strip_prefix("string ") {
        return format!("the string {}", crate::files::shorten(s, ECHO));
    }
    if let Some(v) = quoted(got) {
        if got.starts_with("floating point") || got.starts_with("integer") {
            return format!("the number {v}");
        }
        if got.starts_with("boolean") {
            return v;
        }
    }
    match got {
        "sequence" => "a list".into(),
        "map" => "a table".into(),
        _ => crate::files::shorten(got, ECHO),
    }
}

/// A TOML error of `text` in plain words: "line L: `key`: reason", the key
/// being the dotted path of the line the error points at (`training.batch`,
/// `effects[2].scheme`), then the line itself, shortened.
pub fn toml_error(e: &toml::de::Error, text: &str) -> String {
    let Some(span) = e.span() else { return plain_with_key(e.message()) };
    let at = span.start.min(text.len());
    let line = text[..at].matches('\n').count() + 1;
    let source = text[text[..at].rfind('\n').map_or(0, |i| i + 1)..].lines().next().unwrap_or("");
    let (key, reason) = plain(e.message());
    // Whatever the parser's message quoted, the line stays readable.
    let reason = crate::files::shorten(&reason, 6 * ECHO);
    // A header is the key only of what concerns the table itself (a
    // syntax error noticed there belongs to the lines before it).
    let on_header = source.trim_start().starts_with('[');
    let about_table = reason.starts_with("unknown key") || reason.starts_with("missing key") || reason.starts_with("expected a");
    let path = if on_header && !about_table { None } else { key_at(text, at) };
    let key = match (path, key) {
        (Some(p), Some(k)) if !p.ends_with(&k) => Some(format!("{p}.{k}")),
        (Some(p), _) => Some(p),
        (None, k) => k,
    };
    let quoted = format!("\n  {line} | {}", crate::files::shorten(source.trim_end(), 2 * ECHO));
    // A key is the user's text too: cut like any echoed value.
    match key.map(|k| crate::files::shorten(&k, ECHO)) {
        Some(k) => format!("line {line}: `{k}`: {reason}{quoted}"),
        None => format!("line {line}: {reason}{quoted}"),
    }
}

/// The dotted key of the line holding byte `at` of a TOML text: the last
/// table header before it (`[[name]]` counted, as `name[k]`) and the key
/// of the line. `None` when the line has neither.
fn key_at(text: &str, at: usize) -> Option<String> {
    let start = text[..at].rfind('\n').map_or(0, |i| i + 1);
    let line = text[start..].lines().next().unwrap_or("").trim();
    let header = |l: &str| -> Option<(String, bool)> {
        let l = l.trim();
        if let Some(name) = l.strip_prefix("[[").and_then(|r| r.split("]]").next()) {
            Some((name.trim().to_string(), true))
        } else {
            l.strip_prefix('[').and_then(|r| r.split(']').next()).map(|name| (name.trim().to_string(), false))
        }
    };
    if let Some((name, _)) = header(line) {
        return Some(name);
    }
    let own = line.split_once('=').map(|(k, _)| k.trim().trim_matches('"').to_string()).filter(|k| !k.is_empty() && !k.contains(' '));
    let mut table: Option<String> = None;
    for l in text[..start].lines().rev() {
        if let Some((name, array)) = header(l) {
            table = Some(if array {
                let k = text[..start].lines().filter(|x| header(x).is_some_and(|(n, a)| a && n == name)).count();
                format!("{name}[{}]", k.saturating_sub(1))
            } else {
                name
            });
            break;
        }
    }
    match (table, own) {
        (Some(t), Some(k)) => Some(format!("{t}.{k}")),
        (None, Some(k)) => Some(k),
        (t, None) => t,
    }
}
