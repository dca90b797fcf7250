//! Portable Float Map: `Pf` (1 channel), width and height, scale (negative: little endian), then
//! rows from the bottom up. Invalid values are written as they are (NaN).

use std::io::{self, BufRead, BufReader, Read, Write};
use std::path::Path;

use crate::payload::FloatMap;

/// Writes a one-channel little-endian PFM.
pub fn write_pfm(path: &Path, map: &FloatMap) -> io::Result<()> {
    let mut out = io::BufWriter::new(std::fs::File::create(path)?);
    write!(out, "Pf\n{} {}\n-1.0\n", map.width, map.height)?;
    let w = map.width as usize;
    for row in map.data.chunks_exact(w.max(1)).rev() {
        for v in row {
            out.write_all(&v.to_le_bytes())?;
        }
    }
    out.flush()
}

/// Writes a three-channel little-endian PFM (`PF`), e.g. a point per pixel.
pub fn write_pfm3(path: &Path, width: u32, height: u32, data: &[[f32; 3]]) -> io::Result<()> {
    if data.len() != width as usize * height as usize {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "data does not match width x height",
        ));
    }
    let mut out = io::BufWriter::new(std::fs::File::create(path)?);
    write!(out, "PF\n{width} {height}\n-1.0\n")?;
    for row in data.chunks_exact((width as usize).max(1)).rev() {
        for p in row {
            for v in p {
                out.write_all(&v.to_le_bytes())?;
            }
        }
    }
    out.flush()
}

/// Reads a one-channel PFM of either byte order.
pub fn read_pfm(path: &Path) -> io::Result<FloatMap> {
    let bad = |m: String| {
        io::Error::new(
            io::ErrorKind::InvalidData,
            format!("{}: {m}", path.display()),
        )
    };
    let mut r = BufReader::new(std::fs::File::open(path)?);
    let mut header = Vec::new();
    let mut line = String::new();
    while header.len() < 3 {
        line.clear();
        if r.read_line(&mut line)? == 0 {
            return Err(bad("truncated header".into()));
        }
        header.extend(line.split_whitespace().map(str::to_owned));
        if header.len() == 4 {
            break;
        }
    }
    if header.len() < 4 {
        line.clear();
        r.read_line(&mut line)?;
        header.extend(line.split_whitespace().map(str::to_owned));
    }
    if header.first().map(String::as_str) != Some("Pf") {
        return Err(bad("not a one-channel PFM (`Pf`)".into()));
    }
    let num = |i: usize| header.get(i).ok_or_else(|| bad("truncated header".into()));
    let width: u32 = num(1)?.parse().map_err(|_| bad("bad width".into()))?;
    let height: u32 = num(2)?.parse().map_err(|_| bad("bad height".into()))?;
    let scale: f32 = num(3)?.parse().map_err(|_| bad("bad scale".into()))?;
    let n = width as usize * height as usize;
    let mut bytes = vec![0u8; n * 4];
    r.read_exact(&mut bytes)
        .map_err(|e| bad(format!("pixel data: {e}")))?;
    let vals: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| {
            let b = [b[0], b[1], b[2], b[3]];
            if scale < 0.0 {
                f32::from_le_bytes(b)
            } else {
                f32::from_be_bytes(b)
            }
        })
        .collect();
    let w = width as usize;
    let mut data = Vec::with_capacity(n);
    for row in vals.chunks_exact(w.max(1)).rev() {
        data.extend_from_slice(row);
    }
    Ok(FloatMap {
        width,
        height,
        data,
    })
}
