//! PNG encoding and resizing of RGB8 images read in place from shared memory.

/// Encodes tightly packed RGB8 as PNG with fast compression (observation latency matters more
/// than bytes here).
pub fn encode_png(rgb: &[u8], width: u32, height: u32) -> Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::with_capacity(rgb.len() / 2);
    {
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_compression(png::Compression::Fast);
        let mut w = enc.write_header()?;
        w.write_image_data(rgb)?;
    }
    Ok(out)
}

/// Bilinear resize of packed RGB8 (pixel centres aligned).
pub fn resize_rgb(src: &[u8], sw: u32, sh: u32, dw: u32, dh: u32) -> Vec<u8> {
    let (sw, sh, dw, dh) = (sw as usize, sh as usize, dw as usize, dh as usize);
    let mut out = vec![0u8; dw * dh * 3];
    let sx = sw as f64 / dw as f64;
    let sy = sh as f64 / dh as f64;
    for y in 0..dh {
        let fy = ((y as f64 + 0.5) * sy - 0.5).clamp(0.0, (sh - 1) as f64);
        let (y0, ty) = (fy.floor() as usize, fy - fy.floor());
        let y1 = (y0 + 1).min(sh - 1);
        for x in 0..dw {
            let fx = ((x as f64 + 0.5) * sx - 0.5).clamp(0.0, (sw - 1) as f64);
            let (x0, tx) = (fx.floor() as usize, fx - fx.floor());
            let x1 = (x0 + 1).min(sw - 1);
            for c in 0..3 {
                let p = |xx: usize, yy: usize| src[(yy * sw + xx) * 3 + c] as f64;
                let top = p(x0, y0) * (1.0 - tx) + p(x1, y0) * tx;
                let bot = p(x0, y1) * (1.0 - tx) + p(x1, y1) * tx;
                out[(y * dw + x) * 3 + c] = (top * (1.0 - ty) + bot * ty).round() as u8;
            }
        }
    }
    out
}

/// Nearest-neighbour resize of a depth plane: interpolating across an object's edge would
/// invent depths that exist nowhere in the scene.
pub fn resize_depth(src: &[f32], sw: u32, sh: u32, dw: u32, dh: u32) -> Vec<f32> {
    let (sw, sh, dw, dh) = (sw as usize, sh as usize, dw as usize, dh as usize);
    let mut out = Vec::with_capacity(dw * dh);
    for y in 0..dh {
        let sy = ((y * 2 + 1) * sh / (dh * 2)).min(sh - 1);
        for x in 0..dw {
            let sx = ((x * 2 + 1) * sw / (dw * 2)).min(sw - 1);
            out.push(src[sy * sw + sx]);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_round_trips_through_the_decoder() {
        let (w, h) = (7u32, 5u32);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 7 % 251) as u8).collect();
        let png_bytes = encode_png(&rgb, w, h).expect("encodes");
        let dec = png::Decoder::new(std::io::Cursor::new(png_bytes));
        let mut reader = dec.read_info().expect("header");
        let mut buf = vec![0; reader.output_buffer_size().expect("size")];
        let info = reader.next_frame(&mut buf).expect("frame");
        assert_eq!((info.width, info.height), (w, h));
        assert_eq!(&buf[..rgb.len()], &rgb[..]);
    }

    #[test]
    fn resize_keeps_a_flat_colour_and_the_size() {
        let src = [10u8, 20, 30].repeat(8 * 6);
        let out = resize_rgb(&src, 8, 6, 3, 2);
        assert_eq!(out.len(), 3 * 2 * 3);
        assert!(out.chunks(3).all(|p| p == [10, 20, 30]));
    }

    #[test]
    fn depth_resizes_by_nearest_neighbour_without_inventing_depths() {
        // A 4x2 plane with an edge between 1 m and 2 m: halving keeps only those two values.
        let src = [1.0, 1.0, 2.0, 2.0, 1.0, 1.0, 2.0, 2.0];
        assert_eq!(super::resize_depth(&src, 4, 2, 2, 1), vec![1.0, 2.0]);
        assert_eq!(super::resize_depth(&src, 4, 2, 8, 2).len(), 16);
    }
}
