//! User text as messages show it: control characters and bidirectional
//! overrides escaped, long text cut with the rest counted. One place, so
//! that a script's log line, a config error, a request's echoed path and
//! a material name are all made safe the same way.

/// User text as a message shows it: at most `max` of its characters, the
/// rest counted ("… (N more characters)"), with control characters
/// escaped. The text is cut before it is escaped, so an escape is never
/// cut in half (`\u{20…`).
pub fn shown(text: &str, max: usize) -> String {
    let n = text.chars().count();
    if n <= max {
        return escape_controls(text, false).into_owned();
    }
    let end = text.char_indices().nth(max).map_or(text.len(), |(i, _)| i);
    format!(
        "{}… ({} more characters)",
        escape_controls(&text[..end], false),
        n - max
    )
}

/// Text from a script (a `log` line, an error message) made safe for one
/// line of the daemon's log: control characters and bidirectional
/// overrides become escapes (`\n`, `\u{1b}`, `\u{202e}`), so a script
/// cannot forge log lines, drive the terminal or reverse text on screen.
/// `keep_tab` keeps tabs (they separate `log`'s arguments).
pub fn escape_controls(text: &str, keep_tab: bool) -> std::borrow::Cow<'_, str> {
    // Bidirectional overrides and marks too (regression, hostile probe:
    // U+202E reversed the rest of a log line on screen).
    let escaped = |c: char| {
        (c.is_control() && !(keep_tab && c == '\t'))
            || matches!(c, '\u{061c}' | '\u{200e}' | '\u{200f}' | '\u{2028}'..='\u{202e}' | '\u{2066}'..='\u{2069}')
    };
    if !text.chars().any(escaped) {
        return std::borrow::Cow::Borrowed(text);
    }
    std::borrow::Cow::Owned(
        text.chars()
            .map(|c| {
                if escaped(c) {
                    c.escape_default().to_string()
                } else {
                    c.to_string()
                }
            })
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (hostile probe): a right-to-left override from a script
    /// reversed the rest of its log line on screen.
    #[test]
    fn bidirectional_overrides_are_escaped() {
        assert_eq!(
            escape_controls("a\u{202e}b\u{2066}c\u{200f}", false),
            "a\\u{202e}b\\u{2066}c\\u{200f}"
        );
        assert_eq!(escape_controls("plain — ünïcode", false), "plain — ünïcode");
    }

    /// Long text is cut at `max` characters (not bytes) and the rest
    /// counted; control characters are escaped first.
    #[test]
    fn long_text_is_cut_by_characters_and_counted() {
        assert_eq!(shown("ééé", 2), "éé… (1 more characters)");
        assert_eq!(shown("a\nb", 10), "a\\nb");
        assert_eq!(shown("short", 5), "short");
        // Regression: the cut fell inside an escape ("\u{20…").
        assert_eq!(shown("ab\u{202e}cd", 3), "ab\\u{202e}… (2 more characters)");
    }
}
