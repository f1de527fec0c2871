//! The rule of every error in this workspace: a message leaves its source out,
//! and whoever prints an error prints the whole chain, "a: b: c", so each cause
//! appears once. [`chain`] is that printing; [`assert_cause_once`] is the test
//! each crate runs on its wrapping variants. A message quotes a file's text only
//! through [`excerpt`].

use std::error::Error;

/// An error and its causes on one line, "a: b: c".
pub fn chain(e: &dyn Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        text.push_str(": ");
        text.push_str(&c.to_string());
        cause = c.source();
    }
    text
}

/// At most [`EXCERPT_CHARS`] characters of a file's text, escaped, for an
/// error message: an error names what was wrong and where, and never prints
/// more of a file than that (a file that is not what it claims may hold
/// anything).
pub fn excerpt(text: &str) -> String {
    let mut out: String = text
        .chars()
        .take(EXCERPT_CHARS)
        .flat_map(char::escape_debug)
        .collect();
    if text.chars().nth(EXCERPT_CHARS).is_some() {
        out.push('…');
    }
    out
}

/// The most characters of a file an error message quotes ([`excerpt`]).
pub const EXCERPT_CHARS: usize = 24;

/// For tests: `e` keeps its cause as its source, its own message leaves the
/// cause out, and the chain prints it exactly once. Panics otherwise.
pub fn assert_cause_once(e: &(dyn Error + 'static)) {
    let cause = e
        .source()
        .expect("the error keeps its cause as source")
        .to_string();
    assert!(
        !e.to_string().contains(&cause),
        "{e} repeats its source {cause}"
    );
    let text = chain(e);
    assert_eq!(text.matches(&cause).count(), 1, "{text}");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_excerpt_is_short_escaped_and_marked_when_cut() {
        assert_eq!(excerpt("twelve"), "twelve");
        assert_eq!(excerpt("a\tb\u{1b}[31m"), "a\\tb\\u{1b}[31m");
        let long = "x".repeat(EXCERPT_CHARS + 1);
        assert_eq!(excerpt(&long), format!("{}…", "x".repeat(EXCERPT_CHARS)));
        assert_eq!(excerpt(&long[1..]), "x".repeat(EXCERPT_CHARS));
    }

    #[derive(Debug)]
    struct Outer(std::io::Error, bool);

    impl std::fmt::Display for Outer {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            if self.1 {
                write!(f, "reading x: {}", self.0)
            } else {
                write!(f, "reading x")
            }
        }
    }

    impl Error for Outer {
        fn source(&self) -> Option<&(dyn Error + 'static)> {
            Some(&self.0)
        }
    }

    #[test]
    fn the_chain_prints_each_cause_once_and_the_check_catches_a_repeat() {
        let io = || std::io::Error::other("disk on fire");
        assert_eq!(chain(&Outer(io(), false)), "reading x: disk on fire");
        assert_cause_once(&Outer(io(), false));
        let repeated = std::panic::catch_unwind(|| assert_cause_once(&Outer(io(), true)));
        assert!(repeated.is_err());
    }
}
