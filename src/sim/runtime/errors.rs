//! A script's error text made fit for one line of the log and for
//! `/status`: its line number found, its location prefix stripped, object
//! addresses cut to type names, long text cut and control characters
//! escaped.

/// The first `:LINE:` in a Lua error message.
pub fn line_of(msg: &str) -> Option<usize> {
    let mut rest = msg;
    while let Some(i) = rest.find(':') {
        let tail = &rest[i + 1..];
        let digits: String = tail.chars().take_while(|c| c.is_ascii_digit()).collect();
        if !digits.is_empty() && tail[digits.len()..].starts_with(':') {
            return digits.parse().ok();
        }
        rest = tail;
    }
    None
}

/// `msg` with every object address (`table: 0x7f…`, as Luau writes a
/// table, function, buffer, userdata or thread it cannot show otherwise)
/// cut to the type name. An error raised with a table (`error({})`)
/// showed its address, which differs from run to run (regression, hostile
/// probe), as `tostring` no longer does.
pub fn without_addresses(msg: &str) -> std::borrow::Cow<'_, str> {
    const KINDS: [&str; 5] = ["table", "function", "buffer", "userdata", "thread"];
    if !msg.contains(": 0x") {
        return std::borrow::Cow::Borrowed(msg);
    }
    let mut out = String::with_capacity(msg.len());
    let mut rest = msg;
    while let Some(i) = rest.find(": 0x") {
        let (head, tail) = rest.split_at(i);
        let hex = tail[4..].bytes().take_while(u8::is_ascii_hexdigit).count();
        if hex > 0 && KINDS.iter().any(|k| head.ends_with(k)) {
            out.push_str(head);
            rest = &tail[4 + hex..];
        } else {
            out.push_str(head);
            out.push_str(": 0x");
            rest = &tail[4..];
        }
    }
    out.push_str(rest);
    std::borrow::Cow::Owned(out)
}

/// Longest error text kept from a script, in characters.
pub const MAX_ERROR_CHARS: usize = 500;

/// A script's own error text made fit for one line of the log: cut to
/// [`MAX_ERROR_CHARS`] (regression: `error(string.rep("E", 1e7))` was one
/// 10 MB line), its control characters escaped (regression: a CR or a
/// terminal escape in `error(...)` reached stderr raw).
pub(super) fn one_line(msg: &str) -> String {
    let msg = &without_addresses(msg);
    let cut = match msg.char_indices().nth(MAX_ERROR_CHARS) {
        Some((i, _)) => format!("{}… (cut at {MAX_ERROR_CHARS} characters)", &msg[..i]),
        None => msg.to_string(),
    };
    crate::text::escape_controls(&cut, false).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (hostile probe): `error({})` showed the table's address.
    #[test]
    fn error_text_shows_objects_by_type_not_address() {
        assert_eq!(without_addresses("table: 0x7f12ab34cd56"), "table");
        assert_eq!(
            without_addresses("got function: 0xdeadbeef and buffer: 0x1, ok"),
            "got function and buffer, ok"
        );
        // Not an object's address: kept as written.
        assert_eq!(without_addresses("value: 0x10"), "value: 0x10");
        assert_eq!(without_addresses("table: 0x"), "table: 0x");
        assert_eq!(without_addresses("no address"), "no address");
    }
}
