//! Turning finished tiles into images: the final image of each frame (started by the state
//! machine when a job's last tile lands, on a thread of its own) and partial previews. A
//! finished frame is stored as its PNG and its linear f32 pixels, so EXR and PFM can be
//! encoded on request after the tiles are gone.

use std::sync::Arc;

use protocol::JobState;
use tracer_core::{Image, ImageFormat};

use super::{Farm, FarmError, FarmEvent, Result};

/// Where a finished job's PNG of one frame is stored.
enum StoredImage {
    Job,
    Frame(u32),
}

impl Farm {
    /// Assembles a job whose every tile is done, off the caller's thread (PNG encoding of a
    /// large image takes a while).
    pub(super) fn start_assembly(&self, job_id: u64) {
        let Some(farm) = self.me.upgrade() else {
            return;
        };
        let spawned = std::thread::Builder::new()
            .name(format!("assemble-{job_id}"))
            .spawn(move || {
                if let Err(e) = farm.assemble(job_id) {
                    tracing::error!("job {job_id}: assembling the image failed: {e}");
                }
            });
        match spawned {
            Ok(handle) => {
                let mut running = self.assemblies.lock().unwrap_or_else(|p| p.into_inner());
                running.retain(|h| !h.is_finished());
                running.push(handle);
            }
            // No thread to spare: assemble here rather than leave the job running forever.
            Err(_) => {
                if let Err(e) = self.assemble(job_id) {
                    tracing::error!("job {job_id}: assembling the image failed: {e}");
                }
            }
        }
    }

    /// Assembles on this thread (a pass end already runs on its own).
    pub(super) fn assemble_now(&self, job_id: u64) {
        if let Err(e) = self.assemble(job_id) {
            tracing::error!("job {job_id}: assembling the image failed: {e}");
        }
    }

    /// Waits for every assembly started so far (tests, and a clean shutdown).
    pub fn wait_for_assemblies(&self) {
        let handles: Vec<_> =
            std::mem::take(&mut *self.assemblies.lock().unwrap_or_else(|p| p.into_inner()));
        for handle in handles {
            let _ = handle.join();
        }
    }

    /// Writes a finished job's PNGs from its tiles and marks it done; if the image cannot be
    /// built (a tile file unreadable, the disk full) the job fails with that error rather than
    /// staying "running" forever.
    fn assemble(&self, job_id: u64) -> Result<()> {
        match self.write_image(job_id) {
            Ok(()) => {
                let now = self.now_ms();
                let mut state = self.lock();
                state.mark_done(job_id, now)?;
                let job = state.job(job_id)?;
                let elapsed = job
                    .started_ms
                    .map_or(0.0, |s| now.saturating_sub(s) as f64 / 1000.0);
                drop(state);
                self.flush()?;
                tracing::info!("job {job_id}: done in {elapsed:.2}s");
                self.events.send(FarmEvent::Job(job_id));
                Ok(())
            }
            Err(FarmError::NotFound(e)) => Err(FarmError::NotFound(e)),
            Err(e) => {
                let error = format!("assembling the image failed: {e}");
                tracing::error!("job {job_id}: {error}");
                let now = self.now_ms();
                let ended = self.lock().end_job(
                    job_id,
                    JobState::Failed,
                    Some(error),
                    now,
                    "the job failed",
                );
                if ended.is_ok() && self.flush().is_ok() {
                    self.events.send(FarmEvent::Job(job_id));
                }
                Err(e)
            }
        }
    }

    fn write_image(&self, job_id: u64) -> Result<()> {
        // A progressive job's image is its last finished pass.
        if let Some(image) = self.progressive_image(job_id)? {
            self.files
                .put_image(job_id, &image.to_png(), Arc::new(image))?;
            return Ok(());
        }
        let (grid, frames) = {
            let state = self.lock();
            let job = state.job(job_id)?;
            (
                job.grid,
                job.spec.frames.is_some().then(|| job.spec.frame_list()),
            )
        };
        let tiles_of = |frame: u32| -> Vec<(u32, tracer_core::TileRect)> {
            grid.frame_tiles(frame).map(|t| (t, grid.rect(t))).collect()
        };
        let first = match &frames {
            Some(frames) => {
                let mut first = None;
                for &frame in frames {
                    let image = self.files.assemble(
                        job_id,
                        grid.frame_at(frame),
                        grid.tile_size(),
                        &tiles_of(frame),
                    )?;
                    let png = image.to_png();
                    if first.is_none() {
                        // Kept for the job's image, stored last.
                        self.files
                            .put_frame_image(job_id, frame, &png, image.clone())?;
                        first = Some((png, image));
                    } else {
                        self.files.put_frame_image(job_id, frame, &png, image)?;
                    }
                }
                first.unwrap_or_else(|| (Vec::new(), Arc::new(Image::new(0, 0))))
            }
            None => {
                let image = self.files.assemble(
                    job_id,
                    grid.frame_at(grid.frame(0)),
                    grid.tile_size(),
                    &tiles_of(grid.frame(0)),
                )?;
                (image.to_png(), image)
            }
        };
        // The job's image is its (first) frame, so single-image clients keep working. Last,
        // because storing it drops the tiles.
        self.files.put_image(job_id, &first.0, first.1)?;
        Ok(())
    }

    /// The PNG of one frame of the job; see [`Farm::image_in`]. Blocking.
    pub fn image(&self, job_id: u64, frame: Option<u32>) -> Result<Vec<u8>> {
        self.image_in(job_id, frame, ImageFormat::Png)
    }

    /// One frame of the job (its first frame when `frame` is None) encoded as `format`:
    /// from the stored final image, or assembled from the frame's finished tiles with the
    /// rest black. Blocking.
    pub fn image_in(
        &self,
        job_id: u64,
        frame: Option<u32>,
        format: ImageFormat,
    ) -> Result<Vec<u8>> {
        let (width, height, tile_size, frame_at, tiles, state, stored) = {
            let state = self.lock();
            let job = state.job(job_id)?;
            let first = job.grid.frame(0);
            let frame = match (frame, job.spec.frames) {
                (None, _) => first,
                (Some(f), Some(r)) if (r.first..=r.last).contains(&f) => f,
                (Some(f), None) if f == first => f,
                (Some(f), range) => {
                    return Err(FarmError::NotFound(format!(
                        "job {job_id} has no frame {f} (it renders {})",
                        match range {
                            Some(r) => format!("frames {}..{}", r.first, r.last),
                            None => format!("frame {first}"),
                        }
                    )))
                }
            };
            let tiles: Vec<(u32, tracer_core::TileRect)> = job
                .grid
                .frame_tiles(frame)
                .filter(|&t| job.tiles.is_done(t))
                .map(|t| (t, job.grid.rect(t)))
                .collect();
            // Only frame-range jobs store a PNG per frame; the job image is the first frame.
            let stored = if job.spec.frames.is_some() {
                StoredImage::Frame(frame)
            } else {
                StoredImage::Job
            };
            (
                job.spec.render.width,
                job.spec.render.height,
                job.grid.tile_size(),
                job.grid.frame_at(frame),
                tiles,
                job.state,
                stored,
            )
        };
        if state != JobState::Done {
            if let Some(image) = self.progressive_image(job_id)? {
                return Ok(image.encode(format));
            }
        }
        if state == JobState::Done {
            if format == ImageFormat::Png {
                let png = match stored {
                    StoredImage::Job => self.files.image(job_id)?,
                    StoredImage::Frame(f) => self.files.frame_image(job_id, f)?,
                };
                if let Some(png) = png {
                    return Ok(png);
                }
            } else {
                let linear = match stored {
                    StoredImage::Job => self.files.linear_image(job_id, width, height)?,
                    StoredImage::Frame(f) => {
                        self.files.frame_linear_image(job_id, f, width, height)?
                    }
                };
                match linear {
                    Some(image) => return Ok(image.encode(format)),
                    // Finished by a coordinator that kept only the PNG: the tiles are gone.
                    None if self.files.image(job_id)?.is_some() => {
                        return Err(FarmError::NotFound(format!(
                            "job {job_id} kept only its PNG (it finished before linear \
                             images were stored): no {} is available",
                            format.extension()
                        )))
                    }
                    None => {}
                }
            }
        }
        Ok(self
            .files
            .assemble(job_id, frame_at, tile_size, &tiles)?
            .encode(format))
    }

    /// Every frame's PNG of a finished job, in frame order, as (frame, bytes). Blocking.
    pub fn frame_images(&self, job_id: u64) -> Result<Vec<(u32, Vec<u8>)>> {
        let (frames, state) = {
            let state = self.lock();
            let job = state.job(job_id)?;
            (job.spec.frame_list(), job.state)
        };
        if state != JobState::Done {
            return Err(FarmError::Conflict(format!(
                "job {job_id} is {}: its frames are ready once it is done",
                state.as_str()
            )));
        }
        frames
            .into_iter()
            .map(|f| Ok((f, self.image(job_id, Some(f))?)))
            .collect()
    }
}
