//! Samples of one camera averaged into the camera's image. With `n`
//! samples per camera the display sends camera `c` as frames `c·n` to
//! `c·n + n − 1`, samples 0 to n − 1, and shows frames in order, so a
//! camera's samples arrive one after the other; its image, numbered by
//! the camera, is shown once the last is in: the samples' colours averaged
//! by a [`dray_trace::image::Accumulator`], exactly as `dray render --spp`
//! averages them, with sample 0's depth and ids.

use super::FrameImage;
use dray_trace::image::Accumulator;
use tracing::warn;

/// What adding a frame gave.
#[derive(Debug)]
pub(super) enum Added {
    /// The camera's image: its last sample was in.
    Camera(FrameImage),
    /// More samples of the camera are to come: the frame's pixels, free
    /// for reuse.
    Pending(Vec<[u8; 4]>),
}

/// The samples of the camera being accumulated.
pub(super) struct Samples {
    per_camera: u32,
    width: u32,
    height: u32,
    /// Made with the first frame of a run with more than one sample.
    acc: Option<Accumulator>,
    /// Sample 0's depth and ids.
    depth: Option<Vec<f32>>,
    primid: Option<Vec<u32>>,
}

impl Samples {
    /// `per_camera` samples (0 counts as 1) of `width` × `height` frames.
    pub fn new(per_camera: u32, width: u32, height: u32) -> Samples {
        Samples {
            per_camera: per_camera.max(1),
            width,
            height,
            acc: None,
            depth: None,
            primid: None,
        }
    }

    pub fn per_camera(&self) -> u32 {
        self.per_camera
    }

    /// The camera and the sample of frame `frame`.
    pub fn of(&self, frame: u64) -> (u64, u32) {
        let n = u64::from(self.per_camera);
        (frame / n, (frame % n) as u32)
    }

    /// Adds a frame shown, in frame order.
    pub fn add(&mut self, image: FrameImage) -> Added {
        if self.per_camera == 1 {
            return Added::Camera(image);
        }
        let (camera, sample) = self.of(image.frame);
        let (w, h) = (self.width, self.height);
        let acc = self.acc.get_or_insert_with(|| Accumulator::new(w, h));
        if sample == 0 {
            acc.clear();
            self.depth = image.depth;
            self.primid = image.primid;
        }
        if let Err(e) = acc.add(&image.rgba) {
            warn!(
                frame = image.frame,
                "frame left out of its camera's image: {e}"
            );
        }
        if sample + 1 < self.per_camera {
            return Added::Pending(image.rgba);
        }
        Added::Camera(FrameImage {
            frame: camera,
            width: w,
            height: h,
            rgba: acc.image(),
            depth: self.depth.take(),
            primid: self.primid.take(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(frame: u64, v: u8) -> FrameImage {
        FrameImage {
            frame,
            width: 3,
            height: 2,
            rgba: vec![[v, v / 2, 255 - v, 255]; 6],
            depth: Some(vec![frame as f32; 6]),
            primid: None,
        }
    }

    #[test]
    fn a_camera_s_image_is_the_mean_of_its_samples_with_sample_0_s_depth() {
        let mut s = Samples::new(3, 3, 2);
        assert_eq!(s.of(7), (2, 1));
        let mut images = Vec::new();
        for (f, v) in [(0, 10), (1, 20), (2, 31), (3, 100), (4, 100), (5, 100)] {
            match s.add(frame(f, v)) {
                Added::Camera(img) => images.push(img),
                Added::Pending(rgba) => assert_eq!(rgba.len(), 6),
            }
        }
        assert_eq!(images.len(), 2);
        assert_eq!(images[0].frame, 0);
        assert_eq!(images[0].rgba[0], [20, 10, 235, 255], "the rounded means");
        assert_eq!(images[0].depth, Some(vec![0.0; 6]), "sample 0's depth");
        assert_eq!(images[1].frame, 1);
        assert_eq!(
            images[1].rgba,
            frame(3, 100).rgba,
            "a fresh start per camera"
        );
        assert_eq!(images[1].depth, Some(vec![3.0; 6]));
    }

    #[test]
    fn one_sample_is_the_frame_itself() {
        let mut s = Samples::new(0, 3, 2);
        assert_eq!(s.per_camera(), 1);
        let Added::Camera(img) = s.add(frame(5, 9)) else {
            panic!("one sample completes its camera");
        };
        assert_eq!((img.frame, img.rgba), (5, frame(5, 9).rgba));
    }
}
