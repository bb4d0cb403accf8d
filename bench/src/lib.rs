#![doc = include_str!("../README.md")]

pub mod accept;
pub mod agent;
pub mod all;
pub mod batch;
pub mod control;
pub mod fci;
pub mod ik;
pub mod ipc;
pub mod perception;
pub mod robo;
pub mod sim;
pub mod skills;
pub mod soak;
pub mod tick;

/// Prints a table: a header row and rows of cells, columns padded to fit.
pub fn print_table(header: &[&str], rows: &[Vec<String>]) {
    let mut widths: Vec<usize> = header.iter().map(|h| h.len()).collect();
    for r in rows {
        for (i, c) in r.iter().enumerate() {
            widths[i] = widths[i].max(c.len());
        }
    }
    let line = |cells: Vec<String>| {
        let padded: Vec<String> = cells.iter().enumerate().map(|(i, c)| format!("{c:>w$}", w = widths[i])).collect();
        println!("{}", padded.join("  "));
    };
    line(header.iter().map(|s| s.to_string()).collect());
    for r in rows {
        line(r.clone());
    }
}
