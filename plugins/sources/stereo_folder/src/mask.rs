//! The black border of rectified endoscope images: pixels connected to the image edge whose
//! channels are all at or below a threshold. Found by a flood fill from the edge, so dark
//! tissue inside the image is never masked.

use misslam_framework::{Image, Mask};

/// Valid-region mask of `img`: 0 on the black border, 1 elsewhere.
pub fn border_mask(img: &Image, threshold: u8) -> Mask {
    let (w, h) = (img.width as usize, img.height as usize);
    let c = img.channels as usize;
    let dark = |i: usize| img.data[i * c..i * c + c].iter().all(|&v| v <= threshold);
    let mut data = vec![1u8; w * h];
    let mut stack: Vec<usize> = Vec::new();
    let seed = |i: usize, data: &mut Vec<u8>, stack: &mut Vec<usize>| {
        if data[i] == 1 && dark(i) {
            data[i] = 0;
            stack.push(i);
        }
    };
    for x in 0..w {
        seed(x, &mut data, &mut stack);
        if h > 1 {
            seed((h - 1) * w + x, &mut data, &mut stack);
        }
    }
    for y in 0..h {
        seed(y * w, &mut data, &mut stack);
        if w > 1 {
            seed(y * w + w - 1, &mut data, &mut stack);
        }
    }
    while let Some(i) = stack.pop() {
        let (x, y) = (i % w, i / w);
        if x > 0 {
            seed(i - 1, &mut data, &mut stack);
        }
        if x + 1 < w {
            seed(i + 1, &mut data, &mut stack);
        }
        if y > 0 {
            seed(i - w, &mut data, &mut stack);
        }
        if y + 1 < h {
            seed(i + w, &mut data, &mut stack);
        }
    }
    Mask {
        width: img.width,
        height: img.height,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn border_masked_dark_interior_kept() {
        // 5x4 gray: a black frame on the left column and top row, a dark pixel inside.
        #[rustfmt::skip]
        let px = vec![
            0, 0, 0, 0, 0,
            0, 90, 90, 90, 90,
            0, 90, 2, 90, 90,
            0, 90, 90, 90, 90,
        ];
        let img = Image::new(5, 4, 1, px).unwrap();
        let m = border_mask(&img, 8);
        #[rustfmt::skip]
        let want = vec![
            0, 0, 0, 0, 0,
            0, 1, 1, 1, 1,
            0, 1, 1, 1, 1,
            0, 1, 1, 1, 1,
        ];
        assert_eq!(m.data, want);
    }
}
