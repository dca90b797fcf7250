//! Located errors for graph files: `file:line:column: message`, with the offending line shown.

use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

/// Where a graph error is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Location {
    /// A place in the graph file (1-based line and column).
    File {
        /// Line, from 1.
        line: usize,
        /// Column in characters, from 1.
        column: usize,
    },
    /// A `--set` argument from the command line.
    Override(String),
    /// The file as a whole.
    Whole,
}

/// An error in a graph, naming the file, the line and the field.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct GraphError {
    /// The graph file.
    pub file: PathBuf,
    /// Where in it.
    pub location: Location,
    /// What is wrong, naming the node and field.
    pub message: String,
    /// The offending source line with a caret under the span, when located in the file.
    pub snippet: Option<String>,
}

impl GraphError {
    /// An error at a byte span of the file's text.
    pub fn at(file: &Path, text: &str, span: Range<usize>, message: impl Into<String>) -> Self {
        let (line, column) = line_col(text, span.start);
        let snippet = snippet(text, span, line);
        GraphError {
            file: file.to_owned(),
            location: Location::File { line, column },
            message: message.into(),
            snippet: Some(snippet),
        }
    }

    /// An error caused by a `--set` argument.
    pub fn at_override(file: &Path, arg: &str, message: impl Into<String>) -> Self {
        GraphError {
            file: file.to_owned(),
            location: Location::Override(arg.to_owned()),
            message: message.into(),
            snippet: None,
        }
    }

    /// An error about the whole file.
    pub fn whole(file: &Path, message: impl Into<String>) -> Self {
        GraphError {
            file: file.to_owned(),
            location: Location::Whole,
            message: message.into(),
            snippet: None,
        }
    }

    /// The first line: `file:line:column: message` (what tests pin).
    pub fn headline(&self) -> String {
        let file = self.file.display();
        match &self.location {
            Location::File { line, column } => format!("{file}:{line}:{column}: {}", self.message),
            Location::Override(arg) => format!("{file}: --set {arg}: {}", self.message),
            Location::Whole => format!("{file}: {}", self.message),
        }
    }
}

impl fmt::Display for GraphError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.headline())?;
        if let Some(s) = &self.snippet {
            write!(f, "\n{s}")?;
        }
        Ok(())
    }
}

impl std::error::Error for GraphError {}

/// 1-based line and column (in characters) of a byte offset.
pub fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let offset = offset.min(text.len());
    let before = &text[..floor_char_boundary(text, offset)];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    let column = before[line_start..].chars().count() + 1;
    (line, column)
}

fn floor_char_boundary(text: &str, mut i: usize) -> usize {
    while i > 0 && !text.is_char_boundary(i) {
        i -= 1;
    }
    i
}

fn snippet(text: &str, span: Range<usize>, line: usize) -> String {
    let start = floor_char_boundary(text, span.start.min(text.len()));
    let line_start = text[..start].rfind('\n').map_or(0, |i| i + 1);
    let line_end = text[start..].find('\n').map_or(text.len(), |i| start + i);
    let src = text[line_start..line_end].trim_end_matches('\r');
    let pad = text[line_start..start].chars().count();
    let end = floor_char_boundary(text, span.end.min(line_end).max(start));
    let width = text[start..end].chars().count().max(1);
    let gutter = line.to_string().len();
    format!(
        "{:gutter$} |\n{line} | {src}\n{:gutter$} | {}{}",
        "",
        "",
        " ".repeat(pad),
        "^".repeat(width)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_and_column_are_one_based() {
        let t = "a = 1\nbb = 2\n";
        assert_eq!(line_col(t, 0), (1, 1));
        assert_eq!(line_col(t, 6), (2, 1));
        assert_eq!(line_col(t, 11), (2, 6));
    }

    #[test]
    fn snippet_underlines_the_span() {
        let t = "x = 1\nparams = { paths = \"eight\" }\n";
        let start = t.find("\"eight\"").unwrap();
        let e = GraphError::at(Path::new("g.toml"), t, start..start + 7, "bad");
        assert_eq!(e.headline(), "g.toml:2:20: bad");
        let s = e.snippet.unwrap();
        assert!(
            s.ends_with(&format!("{}{}", " ".repeat(19), "^".repeat(7))),
            "{s}"
        );
    }
}
