//! Markdown tables and the cell formatters the benchmark and validation reports share.
//!
//! A [`Table`] writes GitHub-flavoured pipe tables in one fixed style, `| a | b |` rows under a
//! `|---|---|` separator, so every report looks alike and the separator always has as many
//! columns as the header.

use std::fmt;

/// How a column's cells are aligned, written into the separator row.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Align {
    /// The renderer's default (`---`).
    #[default]
    Default,
    /// Left-aligned (`:---`).
    Left,
    /// Centred (`:---:`).
    Center,
    /// Right-aligned (`---:`).
    Right,
}

impl Align {
    /// The separator-row cell of this alignment.
    fn separator(self) -> &'static str {
        match self {
            Align::Default => "---",
            Align::Left => ":---",
            Align::Center => ":---:",
            Align::Right => "---:",
        }
    }
}

/// A Markdown table: a header row, the separator, then the rows in the order they were added.
///
/// Cells are written as given (callers escape `|` where a value may hold one, e.g. with
/// [`one_line`]); an empty cell is written as a single space, `| |`.
#[derive(Debug, Clone)]
pub struct Table {
    header: Vec<String>,
    align: Vec<Align>,
    /// The rows already rendered, each ending in a newline.
    body: String,
}

impl Table {
    /// A table with these column headings, every column in the default alignment.
    pub fn new<S: AsRef<str>>(header: impl IntoIterator<Item = S>) -> Self {
        let header: Vec<String> = header.into_iter().map(|h| h.as_ref().to_owned()).collect();
        Table {
            align: vec![Align::Default; header.len()],
            header,
            body: String::new(),
        }
    }

    /// Sets the alignment of column `column` (0-based); columns beyond the header are ignored.
    pub fn align(mut self, column: usize, align: Align) -> Self {
        if let Some(a) = self.align.get_mut(column) {
            *a = align;
        }
        self
    }

    /// Number of columns (header cells).
    pub fn columns(&self) -> usize {
        self.header.len()
    }

    /// Appends a row of cells.
    pub fn row<S: AsRef<str>>(&mut self, cells: impl IntoIterator<Item = S>) -> &mut Self {
        push_row(&mut self.body, cells);
        self
    }

    /// Appends a row whose leading `cells` are given and whose remaining columns are blank:
    /// how a failed or skipped measurement shows its reason in an otherwise empty row.
    pub fn partial_row<S: AsRef<str>>(&mut self, cells: impl IntoIterator<Item = S>) -> &mut Self {
        let mut given = 0;
        self.body.push('|');
        for c in cells {
            push_cell(&mut self.body, c.as_ref());
            given += 1;
        }
        for _ in given..self.columns() {
            push_cell(&mut self.body, "");
        }
        self.body.push('\n');
        self
    }

    /// Appends the table (header, separator, rows) to `out`.
    pub fn write_to(&self, out: &mut String) {
        push_row(out, &self.header);
        out.push('|');
        for a in &self.align {
            out.push_str(a.separator());
            out.push('|');
        }
        out.push('\n');
        out.push_str(&self.body);
    }
}

impl fmt::Display for Table {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut s = String::new();
        self.write_to(&mut s);
        f.write_str(&s)
    }
}

/// Writes `| a | b |` and a newline.
fn push_row<S: AsRef<str>>(out: &mut String, cells: impl IntoIterator<Item = S>) {
    out.push('|');
    for c in cells {
        push_cell(out, c.as_ref());
    }
    out.push('\n');
}

/// Writes ` cell |`, or ` |` for an empty cell.
fn push_cell(out: &mut String, cell: &str) {
    out.push(' ');
    if !cell.is_empty() {
        out.push_str(cell);
        out.push(' ');
    }
    out.push('|');
}

/// The first line of a (possibly multi-line) message.
pub fn first_line(text: &str) -> &str {
    text.lines().next().unwrap_or("")
}

/// The first line of an error message, table-safe: `|` becomes `/`.
pub fn one_line(error: &str) -> String {
    first_line(error).replace('|', "/")
}

/// A byte count in whole MiB (`"12 MiB"`), or `–` when unknown.
pub fn mib(bytes: Option<u64>) -> String {
    bytes.map_or("–".into(), |b| {
        format!("{:.0} MiB", b as f64 / (1u64 << 20) as f64)
    })
}

/// The value formatted by `format`, or `–` when there is none.
pub fn or_dash<T>(value: Option<T>, format: impl FnOnce(T) -> String) -> String {
    value.map_or_else(|| "–".into(), format)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_separator_and_rows() {
        let mut t = Table::new(["Block", "Elements", "ms"]);
        t.row(["8³", "512", "1.25"]);
        t.row(vec![
            String::from("16³"),
            4096.to_string(),
            format!("{:.2}", 9.5),
        ]);
        assert_eq!(
            t.to_string(),
            "| Block | Elements | ms |\n|---|---|---|\n| 8³ | 512 | 1.25 |\n| 16³ | 4096 | 9.50 |\n"
        );
    }

    #[test]
    fn a_table_without_rows_is_its_header() {
        let t = Table::new(["Target", "Measured", "Met"]);
        assert_eq!(
            t.to_string(),
            "| Target | Measured | Met |\n|---|---|---|\n"
        );
        assert_eq!(t.columns(), 3);
    }

    #[test]
    fn empty_cells_are_one_space_wide() {
        let mut t = Table::new(["a", "b", "c"]);
        t.row(["", "x", ""]);
        assert!(t.to_string().ends_with("| | x | |\n"), "{t}");
    }

    #[test]
    fn partial_rows_are_padded_with_blank_cells() {
        let mut t = Table::new(["Zip", "Slices", "Elements", "s"]);
        t.partial_row(["upload failed"]);
        t.partial_row(["", "", "ccx missing"]);
        let s = t.to_string();
        assert!(s.contains("\n| upload failed | | | |\n"), "{s}");
        assert!(s.ends_with("\n| | | ccx missing | |\n"), "{s}");
    }

    #[test]
    fn alignment_goes_into_the_separator() {
        let t = Table::new(["name", "n", "mid", "plain"])
            .align(0, Align::Left)
            .align(1, Align::Right)
            .align(2, Align::Center)
            .align(9, Align::Right);
        assert_eq!(
            t.to_string(),
            "| name | n | mid | plain |\n|:---|---:|:---:|---|\n"
        );
    }

    #[test]
    fn write_to_appends() {
        let mut out = String::from("## Section\n\n");
        let mut t = Table::new(["k", "v"]);
        t.row(["a", "1"]);
        t.write_to(&mut out);
        assert_eq!(out, "## Section\n\n| k | v |\n|---|---|\n| a | 1 |\n");
    }

    #[test]
    fn error_cells_keep_the_first_line_without_pipes() {
        assert_eq!(
            one_line("solve failed: a | b\nbacktrace"),
            "solve failed: a / b"
        );
        assert_eq!(one_line(""), "");
        assert_eq!(first_line("ccx crashed\ndetails"), "ccx crashed");
    }

    #[test]
    fn cell_formatters() {
        assert_eq!(mib(Some(3 << 20)), "3 MiB");
        assert_eq!(mib(None), "–");
        assert_eq!(or_dash(Some(1.234), |v| format!("{v:.2}")), "1.23");
        assert_eq!(or_dash(None::<f64>, |v| format!("{v:.2}")), "–");
    }
}
