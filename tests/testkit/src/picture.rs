//! What a PNG picture holds, as numbers a test can check: its size, how much of it is not
//! background, how many colours it uses.

use std::path::Path;

/// Pixel statistics of a PNG file.
#[derive(Debug, Clone, PartialEq)]
pub struct PngStats {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Fraction of pixels that differ from the top-left pixel (the background).
    pub drawn: f64,
    /// Distinct RGB colours (counted up to 4096).
    pub colours: usize,
}

/// Reads `path` (8-bit RGB or RGBA) into [`PngStats`].
pub fn png_stats(path: &Path) -> Result<PngStats, String> {
    let file = std::fs::File::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader
        .next_frame(&mut buf)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    let step = match info.color_type {
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        other => return Err(format!("{}: colour type {other:?}", path.display())),
    };
    let pixels: Vec<&[u8]> = buf[..info.buffer_size()]
        .chunks_exact(step)
        .map(|p| &p[..3])
        .collect();
    let background = pixels.first().copied().unwrap_or(&[0, 0, 0]);
    let drawn = pixels.iter().filter(|p| **p != background).count();
    let mut colours = std::collections::HashSet::new();
    for p in &pixels {
        if colours.len() < 4096 {
            colours.insert(p.to_vec());
        }
    }
    Ok(PngStats {
        width: info.width,
        height: info.height,
        drawn: drawn as f64 / pixels.len().max(1) as f64,
        colours: colours.len(),
    })
}
