//! The farm's tunables and the limits that keep one submission from exhausting it.

use std::time::Duration;

use protocol::JobSpec;
use tracer_core::scene::LoadLimits;

use crate::farm::TileGrid;

/// Upper bounds on what a job may ask for; each breach is a 4xx with the limit in its message.
#[derive(Clone, Debug)]
pub struct Limits {
    /// The whole multipart body, scene and assets included.
    pub max_upload_bytes: usize,
    /// Width and height each.
    pub max_dimension: u32,
    /// Width × height.
    pub max_pixels: u64,
    pub max_spp: u32,
    pub max_depth: u32,
    pub min_tile_size: u32,
    pub max_tile_size: u32,
    /// Frames in one frame-range job.
    pub max_frames: u32,
    /// Tiles in one job, every frame counted (`--max-job-tiles`): each costs a bit of memory
    /// and, when it runs, a lease and a file.
    pub max_job_tiles: u64,
    /// Decoded pixels of all the textures a scene uses, read from each PNG's header before it
    /// is decoded.
    pub max_texture_pixels: u64,
    /// Spheres, triangles and each distinct mesh's triangles in one scene: what its geometry
    /// and BVHs cost in memory (tracer-core also bounds the scene file's XML elements by it).
    pub max_scene_primitives: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_upload_bytes: 256 << 20,
            max_dimension: 16_384,
            max_pixels: 64 << 20,
            max_spp: 16_384,
            max_depth: 64,
            min_tile_size: 4,
            max_tile_size: 1024,
            max_frames: 10_000,
            max_job_tiles: 1_000_000,
            // Tighter than tracer-core's own defaults: a farm loads up to `--max-scene-builds`
            // scenes at once for strangers, and the worst case costs ~6 B per texture pixel and
            // ~2 KiB per XML sphere (docs/farm.md, "Memory under hostile submissions").
            max_texture_pixels: 64_000_000,
            max_scene_primitives: 1_000_000,
        }
    }
}

impl Limits {
    /// The scene budgets, as tracer-core's loader takes them.
    pub fn load_limits(&self) -> LoadLimits {
        LoadLimits {
            max_texture_pixels: self.max_texture_pixels,
            max_primitives: self.max_scene_primitives,
        }
    }

    /// Checks a job's tile count (frames × tiles per frame) against the budget.
    pub fn check_tiles(&self, grid: &TileGrid) -> Result<(), String> {
        let tiles = grid.total_u64();
        // A tile index is a u32 however high the budget is set.
        let limit = self.max_job_tiles.min(u32::MAX as u64);
        if tiles > limit {
            return Err(format!(
                "the job has {tiles} tiles ({} per frame), over the limit of {limit} tiles per \
                 job (--max-job-tiles); use fewer frames or a larger tile_size",
                grid.per_frame()
            ));
        }
        Ok(())
    }

    /// Checks a job's settings against the limits and tracer-core's own validation.
    pub fn check(&self, spec: &JobSpec) -> Result<(), String> {
        let s = &spec.render;
        s.validate().map_err(|e| e.to_string())?;
        if s.width > self.max_dimension || s.height > self.max_dimension {
            return Err(format!(
                "image size {}x{} exceeds the limit of {} pixels per side",
                s.width, s.height, self.max_dimension
            ));
        }
        if s.width as u64 * s.height as u64 > self.max_pixels {
            return Err(format!(
                "image size {}x{} exceeds the limit of {} pixels",
                s.width, s.height, self.max_pixels
            ));
        }
        if let Some(a) = &spec.adaptive {
            if a.spp_max > self.max_spp {
                return Err(format!(
                    "adaptive spp_max {} exceeds the limit of {} spp",
                    a.spp_max, self.max_spp
                ));
            }
        }
        if s.spp > self.max_spp {
            return Err(format!(
                "spp {} exceeds the limit of {}",
                s.spp, self.max_spp
            ));
        }
        if s.max_depth == 0 || s.max_depth > self.max_depth {
            return Err(format!(
                "max_depth {} must be between 1 and {}",
                s.max_depth, self.max_depth
            ));
        }
        if spec.tile_size < self.min_tile_size || spec.tile_size > self.max_tile_size {
            return Err(format!(
                "tile_size {} must be between {} and {}",
                spec.tile_size, self.min_tile_size, self.max_tile_size
            ));
        }
        if let Some(range) = spec.frames {
            if range.is_empty() || range.len() > self.max_frames {
                return Err(format!(
                    "frames {}..{} must hold between 1 and {} frames",
                    range.first, range.last, self.max_frames
                ));
            }
        }
        self.check_tiles(&TileGrid::new(spec))?;
        if let Some(name) = &spec.name {
            if name.len() > 200 {
                return Err("a job name is at most 200 bytes".into());
            }
        }
        Ok(())
    }
}

/// How the farm schedules and expires work.
#[derive(Clone, Debug)]
pub struct FarmConfig {
    /// A lease lapses this long after it was granted or last heartbeat.
    pub lease_timeout: Duration,
    /// How often workers heartbeat; also how fast a cancel reaches them.
    pub heartbeat: Duration,
    /// The longest a lease request is held open waiting for work.
    pub max_poll_wait: Duration,
    /// After a restart, leases granted before it get this long to be heartbeat or completed.
    pub restart_grace: Duration,
    /// Hand idle workers copies of slow outstanding tiles when nothing is queued.
    pub stragglers: bool,
    /// A tile fails its job after failing on this many different workers...
    pub max_tile_workers: usize,
    /// ...or this many times in all (a farm of one worker must also give up).
    pub max_tile_attempts: usize,
    /// Worker identities kept (`--max-workers`); registering beyond it forgets the
    /// longest-silent worker that holds no lease.
    pub max_workers: usize,
    pub limits: Limits,
    pub connections: ConnectionLimits,
}

impl Default for FarmConfig {
    fn default() -> Self {
        Self {
            lease_timeout: Duration::from_secs(5),
            heartbeat: Duration::from_secs(1),
            max_poll_wait: Duration::from_secs(30),
            restart_grace: Duration::from_secs(15),
            stragglers: true,
            max_tile_workers: 3,
            max_tile_attempts: 5,
            max_workers: 10_000,
            limits: Limits::default(),
            connections: ConnectionLimits::default(),
        }
    }
}

/// How the HTTP server treats connections, so that clients that send slowly, or not at all,
/// cannot hold the coordinator's descriptors or memory.
#[derive(Clone, Debug)]
pub struct ConnectionLimits {
    /// A request's head must be complete this long after the connection opened, or after the
    /// first byte of a later request on it arrived.
    pub header_timeout: Duration,
    /// A kept-alive connection that sends nothing for this long after a response is closed;
    /// a submission's upload that pauses this long is abandoned.
    pub idle_timeout: Duration,
    /// Connections served at once; further ones wait in the listen backlog. The server also
    /// keeps it to three quarters of the descriptor limit.
    pub max_connections: usize,
    /// Requests that read an upload or build a scene (submit, resubmit, camera) at once;
    /// further ones wait their turn before their body is read.
    pub max_scene_builds: usize,
}

impl Default for ConnectionLimits {
    fn default() -> Self {
        Self {
            header_timeout: Duration::from_secs(10),
            idle_timeout: Duration::from_secs(60),
            max_connections: 4096,
            max_scene_builds: 2,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_name_what_they_refuse() {
        let limits = Limits::default();
        let mut spec = JobSpec::default();
        assert!(limits.check(&spec).is_ok());
        spec.render.spp = 1_000_000;
        assert!(limits.check(&spec).unwrap_err().contains("spp"));
        spec.render.spp = 4;
        spec.render.width = 100_000;
        assert!(limits.check(&spec).unwrap_err().contains("per side"));
        spec.render.width = 16_000;
        spec.render.height = 16_000;
        assert!(limits.check(&spec).unwrap_err().contains("pixels"));
        spec.render.height = 10;
        spec.tile_size = 1;
        assert!(limits.check(&spec).unwrap_err().contains("tile_size"));
        spec.tile_size = 64;
        spec.render.max_depth = 1000;
        assert!(limits.check(&spec).unwrap_err().contains("max_depth"));
        spec.render.max_depth = 5;
        spec.render.width = 0;
        assert!(limits.check(&spec).is_err());
        spec.render.width = 8192;
        spec.render.height = 8192;
        spec.tile_size = 8;
        assert!(limits.check(&spec).unwrap_err().contains("--max-job-tiles"));
        spec.tile_size = 16;
        assert!(limits.check(&spec).is_ok(), "262144 tiles fit");
        spec.frames = Some(tracer_core::FrameRange::new(0, 9).unwrap());
        assert!(limits.check(&spec).unwrap_err().contains("2621440 tiles"));
    }
}
