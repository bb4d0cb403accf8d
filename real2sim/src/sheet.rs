//! A contact sheet: the agentview image of each gym's start, downscaled and tiled into one PNG.
//! Rendered in process with sim-host's offscreen renderer (EGL); nothing else in Real2Sim
//! renders.

use std::path::Path;

use sim_host::render::Cameras;
use sim_host::Sim;

use crate::{Error, Result};

/// Width and height of one tile.
pub const TILE: (usize, usize) = (240, 180);

/// The start of a gym seen by its `camera` (RGB, row-major), at the camera's size.
pub fn first_frame(scene_path: &Path, camera: &str) -> Result<(Vec<u8>, usize, usize)> {
    let sim = Sim::load(scene_path).map_err(|e| Error::Episode(e.into()))?;
    let spec = sim
        .scene
        .cameras
        .iter()
        .find(|c| c.name == camera)
        .ok_or_else(|| Error::Episode(anyhow::anyhow!("{}: no camera '{camera}'", scene_path.display())))?;
    let (w, h) = (spec.width, spec.height);
    let id = sim.layout.cameras.iter().find(|(n, _)| n == camera).map(|c| c.1).unwrap_or(0);
    let mut cams = Cameras::new(sim.model.clone(), w, h, false)?;
    cams.set_state(sim.qpos(), 0.0);
    let (rgb, _) = cams.render(id)?;
    Ok((rgb.to_vec(), w as usize, h as usize))
}

/// Box-filters an RGB image down (or up, by repeating pixels) to the tile size.
pub fn shrink(rgb: &[u8], w: usize, h: usize) -> Vec<u8> {
    let (tw, th) = TILE;
    let mut out = vec![0u8; tw * th * 3];
    for ty in 0..th {
        let (y0, y1) = (ty * h / th, ((ty + 1) * h / th).max(ty * h / th + 1));
        for tx in 0..tw {
            let (x0, x1) = (tx * w / tw, ((tx + 1) * w / tw).max(tx * w / tw + 1));
            let mut acc = [0u32; 3];
            for y in y0..y1.min(h) {
                for x in x0..x1.min(w) {
                    for c in 0..3 {
                        acc[c] += rgb[(y * w + x) * 3 + c] as u32;
                    }
                }
            }
            let n = ((y1.min(h) - y0) * (x1.min(w) - x0)).max(1) as u32;
            for c in 0..3 {
                out[(ty * tw + tx) * 3 + c] = (acc[c] / n) as u8;
            }
        }
    }
    out
}

/// Tiles the agentview starts of `scenes` (at most `columns` a row) into a PNG at `out`.
pub fn write(scenes: &[&Path], columns: usize, out: &Path) -> Result<usize> {
    let mut tiles = Vec::with_capacity(scenes.len());
    for scene in scenes {
        let (rgb, w, h) = first_frame(scene, "agentview")?;
        tiles.push(shrink(&rgb, w, h));
    }
    write_tiles(&tiles, columns, out)?;
    Ok(scenes.len())
}

/// Writes tiles of [`TILE`] size (RGB, as [`shrink`] makes them), `columns` a row, left to right
/// and top to bottom, into one PNG at `out` (written whole, then renamed).
pub fn write_tiles(tiles: &[Vec<u8>], columns: usize, out: &Path) -> Result<()> {
    let (tw, th) = TILE;
    let cols = columns.max(1).min(tiles.len().max(1));
    let rows = tiles.len().div_ceil(cols).max(1);
    let (sw, sh) = (cols * tw, rows * th);
    let mut sheet = vec![32u8; sw * sh * 3];
    for (i, tile) in tiles.iter().enumerate() {
        if tile.len() != tw * th * 3 {
            return Err(Error::Episode(anyhow::anyhow!("tile {i} is not {tw}x{th} RGB")));
        }
        let (ox, oy) = ((i % cols) * tw, (i / cols) * th);
        for y in 0..th {
            let dst = ((oy + y) * sw + ox) * 3;
            sheet[dst..dst + tw * 3].copy_from_slice(&tile[y * tw * 3..(y + 1) * tw * 3]);
        }
    }
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, sw as u32, sh as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().map_err(|e| Error::Episode(e.into()))?;
        w.write_image_data(&sheet).map_err(|e| Error::Episode(e.into()))?;
    }
    lockstep::demo::write_atomic(out, &bytes)?;
    Ok(())
}
