//! SQLite: jobs, their assets, finished tiles, tile failures and live leases. Numbered
//! migrations run at start-up. One connection, in WAL mode, locked exclusively so a second
//! coordinator cannot open the same data dir.
//!
//! Durability: `synchronous=NORMAL` survives a killed process (the kill -9 test) but may lose
//! the last transactions on power loss; finished tiles then render again, nothing breaks.

use std::path::Path;

use rusqlite::{params, Connection, OptionalExtension};
use worker::protocol::{BundleFile, JobSpec, JobState, TileFailure};

use super::StoreError;

/// Each entry upgrades the schema by one version (`PRAGMA user_version`).
const MIGRATIONS: &[&str] = &[
    // 1: the initial schema.
    "CREATE TABLE jobs (
        id INTEGER PRIMARY KEY,
        name TEXT NOT NULL,
        scene_file TEXT NOT NULL,
        scene_hash TEXT NOT NULL,
        spec TEXT NOT NULL,
        state TEXT NOT NULL,
        error TEXT,
        created_ms INTEGER NOT NULL,
        started_ms INTEGER,
        finished_ms INTEGER
    );
    CREATE TABLE job_assets (
        job_id INTEGER NOT NULL,
        path TEXT NOT NULL,
        hash TEXT NOT NULL,
        size INTEGER NOT NULL,
        PRIMARY KEY (job_id, path)
    ) WITHOUT ROWID;
    CREATE TABLE tiles_done (
        job_id INTEGER NOT NULL,
        tile INTEGER NOT NULL,
        PRIMARY KEY (job_id, tile)
    ) WITHOUT ROWID;
    CREATE TABLE tile_failures (
        job_id INTEGER NOT NULL,
        tile INTEGER NOT NULL,
        worker TEXT NOT NULL,
        error TEXT NOT NULL,
        at_ms INTEGER NOT NULL
    );
    CREATE INDEX tile_failures_job ON tile_failures (job_id);
    CREATE TABLE leases (
        id INTEGER PRIMARY KEY,
        job_id INTEGER NOT NULL,
        tile INTEGER NOT NULL,
        worker TEXT NOT NULL,
        granted_ms INTEGER NOT NULL
    );
    CREATE TABLE meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL) WITHOUT ROWID;",
];

pub struct Db {
    conn: Connection,
}

/// A job as stored, with what a restart needs to resume it.
#[derive(Clone, Debug)]
pub struct StoredJob {
    pub id: u64,
    pub name: String,
    pub scene_file: String,
    pub scene_hash: String,
    pub spec: JobSpec,
    pub state: JobState,
    pub error: Option<String>,
    pub created_ms: u64,
    pub started_ms: Option<u64>,
    pub finished_ms: Option<u64>,
    pub assets: Vec<BundleFile>,
    pub tiles_done: Vec<u32>,
    pub failures: Vec<TileFailure>,
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StoredLease {
    pub id: u64,
    pub job_id: u64,
    pub tile: u32,
    pub worker: String,
    pub granted_ms: u64,
}

impl Db {
    pub fn open(path: &Path) -> Result<Db, StoreError> {
        let conn = Connection::open(path)?;
        // Exclusive locking also means WAL needs no shared-memory file.
        conn.pragma_update(None, "locking_mode", "EXCLUSIVE")?;
        conn.pragma_update(None, "journal_mode", "WAL")?;
        conn.pragma_update(None, "synchronous", "NORMAL")?;
        Self::init(conn)
    }

    pub fn open_in_memory() -> Result<Db, StoreError> {
        Self::init(Connection::open_in_memory()?)
    }

    fn init(mut conn: Connection) -> Result<Db, StoreError> {
        let version: i64 = conn.pragma_query_value(None, "user_version", |r| r.get(0))?;
        let version = version.max(0) as usize;
        if version > MIGRATIONS.len() {
            return Err(StoreError::Corrupt(format!(
                "the database has schema version {version}, newer than this coordinator's {}",
                MIGRATIONS.len()
            )));
        }
        for (i, sql) in MIGRATIONS.iter().enumerate().skip(version) {
            let tx = conn.transaction()?;
            tx.execute_batch(sql)?;
            tx.pragma_update(None, "user_version", (i + 1) as i64)?;
            tx.commit()?;
        }
        Ok(Db { conn })
    }

    /// Counts coordinator start-ups; lease ids carry it so they never repeat across restarts.
    pub fn next_epoch(&self) -> Result<u64, StoreError> {
        let epoch: i64 = self
            .conn
            .query_row("SELECT value FROM meta WHERE key = 'epoch'", [], |r| {
                r.get(0)
            })
            .optional()?
            .unwrap_or(0)
            + 1;
        self.conn.execute(
            "INSERT INTO meta (key, value) VALUES ('epoch', ?1)
             ON CONFLICT (key) DO UPDATE SET value = excluded.value",
            [epoch],
        )?;
        Ok(epoch as u64)
    }

    /// Inserts a job and its assets; returns its id.
    pub fn insert_job(&mut self, job: &StoredJob) -> Result<u64, StoreError> {
        let spec = serde_json::to_string(&job.spec).expect("a JobSpec always serialises");
        let tx = self.conn.transaction()?;
        tx.execute(
            "INSERT INTO jobs (name, scene_file, scene_hash, spec, state, created_ms)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            params![
                job.name,
                job.scene_file,
                job.scene_hash,
                spec,
                job.state.as_str(),
                job.created_ms as i64
            ],
        )?;
        let id = tx.last_insert_rowid() as u64;
        for asset in &job.assets {
            tx.execute(
                "INSERT INTO job_assets (job_id, path, hash, size) VALUES (?1, ?2, ?3, ?4)",
                params![id as i64, asset.path, asset.hash, asset.size as i64],
            )?;
        }
        tx.commit()?;
        Ok(id)
    }

    pub fn set_job_state(
        &self,
        id: u64,
        state: JobState,
        error: Option<&str>,
        started_ms: Option<u64>,
        finished_ms: Option<u64>,
    ) -> Result<(), StoreError> {
        self.conn
            .prepare_cached(
                "UPDATE jobs SET state = ?2, error = ?3, started_ms = ?4, finished_ms = ?5
                 WHERE id = ?1",
            )?
            .execute(params![
                id as i64,
                state.as_str(),
                error,
                started_ms.map(|v| v as i64),
                finished_ms.map(|v| v as i64)
            ])?;
        Ok(())
    }

    pub fn insert_lease(&self, lease: &StoredLease) -> Result<(), StoreError> {
        self.conn
            .prepare_cached(
                "INSERT INTO leases (id, job_id, tile, worker, granted_ms)
                 VALUES (?1, ?2, ?3, ?4, ?5)",
            )?
            .execute(params![
                lease.id as i64,
                lease.job_id as i64,
                lease.tile,
                lease.worker,
                lease.granted_ms as i64
            ])?;
        Ok(())
    }

    pub fn delete_lease(&self, id: u64) -> Result<(), StoreError> {
        self.conn
            .prepare_cached("DELETE FROM leases WHERE id = ?1")?
            .execute([id as i64])?;
        Ok(())
    }

    pub fn delete_job_leases(&self, job_id: u64) -> Result<(), StoreError> {
        self.conn
            .prepare_cached("DELETE FROM leases WHERE job_id = ?1")?
            .execute([job_id as i64])?;
        Ok(())
    }

    /// Records a finished tile and drops every lease on it, atomically.
    pub fn complete_tile(&mut self, job_id: u64, tile: u32) -> Result<(), StoreError> {
        let tx = self.conn.transaction()?;
        tx.prepare_cached("INSERT OR IGNORE INTO tiles_done (job_id, tile) VALUES (?1, ?2)")?
            .execute(params![job_id as i64, tile])?;
        tx.prepare_cached("DELETE FROM leases WHERE job_id = ?1 AND tile = ?2")?
            .execute(params![job_id as i64, tile])?;
        tx.commit()?;
        Ok(())
    }

    pub fn insert_failure(
        &self,
        job_id: u64,
        failure: &TileFailure,
        at_ms: u64,
    ) -> Result<(), StoreError> {
        self.conn
            .prepare_cached(
                "INSERT INTO tile_failures (job_id, tile, worker, error, at_ms)
                 VALUES (?1, ?2, ?3, ?4, ?5)",
            )?
            .execute(params![
                job_id as i64,
                failure.tile,
                failure.worker,
                failure.error,
                at_ms as i64
            ])?;
        Ok(())
    }

    pub fn clear_failures(&self, job_id: u64) -> Result<(), StoreError> {
        self.conn
            .prepare_cached("DELETE FROM tile_failures WHERE job_id = ?1")?
            .execute([job_id as i64])?;
        Ok(())
    }

    /// Every job, oldest first, with finished tiles and failures.
    pub fn load_jobs(&self) -> Result<Vec<StoredJob>, StoreError> {
        let mut jobs = Vec::new();
        let mut stmt = self.conn.prepare(
            "SELECT id, name, scene_file, scene_hash, spec, state, error, created_ms,
                    started_ms, finished_ms
             FROM jobs ORDER BY id",
        )?;
        let rows = stmt.query_map([], |r| {
            Ok((
                r.get::<_, i64>(0)? as u64,
                r.get::<_, String>(1)?,
                r.get::<_, String>(2)?,
                r.get::<_, String>(3)?,
                r.get::<_, String>(4)?,
                r.get::<_, String>(5)?,
                r.get::<_, Option<String>>(6)?,
                r.get::<_, i64>(7)? as u64,
                r.get::<_, Option<i64>>(8)?.map(|v| v as u64),
                r.get::<_, Option<i64>>(9)?.map(|v| v as u64),
            ))
        })?;
        for row in rows {
            let (id, name, scene_file, scene_hash, spec, state, error, created, started, finished) =
                row?;
            let spec: JobSpec = serde_json::from_str(&spec)
                .map_err(|e| StoreError::Corrupt(format!("job {id}'s settings: {e}")))?;
            let state = JobState::parse(&state)
                .ok_or_else(|| StoreError::Corrupt(format!("job {id}'s state {state:?}")))?;
            jobs.push(StoredJob {
                id,
                name,
                scene_file,
                scene_hash,
                spec,
                state,
                error,
                created_ms: created,
                started_ms: started,
                finished_ms: finished,
                assets: self.job_assets(id)?,
                tiles_done: self.tiles_done(id)?,
                failures: self.failures(id)?,
            });
        }
        Ok(jobs)
    }

    fn job_assets(&self, job_id: u64) -> Result<Vec<BundleFile>, StoreError> {
        let mut stmt = self
            .conn
            .prepare("SELECT path, hash, size FROM job_assets WHERE job_id = ?1 ORDER BY path")?;
        let rows = stmt.query_map([job_id as i64], |r| {
            Ok(BundleFile {
                path: r.get(0)?,
                hash: r.get(1)?,
                size: r.get::<_, i64>(2)? as u64,
            })
        })?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    fn tiles_done(&self, job_id: u64) -> Result<Vec<u32>, StoreError> {
        let mut stmt = self
            .conn
            .prepare("SELECT tile FROM tiles_done WHERE job_id = ?1 ORDER BY tile")?;
        let rows = stmt.query_map([job_id as i64], |r| r.get(0))?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    fn failures(&self, job_id: u64) -> Result<Vec<TileFailure>, StoreError> {
        let mut stmt = self.conn.prepare(
            "SELECT tile, worker, error FROM tile_failures WHERE job_id = ?1 ORDER BY rowid",
        )?;
        let rows = stmt.query_map([job_id as i64], |r| {
            Ok(TileFailure {
                tile: r.get(0)?,
                worker: r.get(1)?,
                error: r.get(2)?,
            })
        })?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    pub fn load_leases(&self) -> Result<Vec<StoredLease>, StoreError> {
        let mut stmt = self
            .conn
            .prepare("SELECT id, job_id, tile, worker, granted_ms FROM leases ORDER BY id")?;
        let rows = stmt.query_map([], |r| {
            Ok(StoredLease {
                id: r.get::<_, i64>(0)? as u64,
                job_id: r.get::<_, i64>(1)? as u64,
                tile: r.get(2)?,
                worker: r.get(3)?,
                granted_ms: r.get::<_, i64>(4)? as u64,
            })
        })?;
        Ok(rows.collect::<Result<_, _>>()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job() -> StoredJob {
        StoredJob {
            id: 0,
            name: "a".into(),
            scene_file: "a.scene".into(),
            scene_hash: "00".into(),
            spec: JobSpec::default(),
            state: JobState::Queued,
            error: None,
            created_ms: 5,
            started_ms: None,
            finished_ms: None,
            assets: vec![BundleFile {
                path: "images/x.png".into(),
                hash: "ab".into(),
                size: 3,
            }],
            tiles_done: vec![],
            failures: vec![],
        }
    }

    #[test]
    fn a_job_round_trips_with_its_progress() {
        let mut db = Db::open_in_memory().unwrap();
        let id = db.insert_job(&job()).unwrap();
        db.insert_lease(&StoredLease {
            id: 9,
            job_id: id,
            tile: 2,
            worker: "w".into(),
            granted_ms: 7,
        })
        .unwrap();
        db.insert_lease(&StoredLease {
            id: 10,
            job_id: id,
            tile: 3,
            worker: "v".into(),
            granted_ms: 8,
        })
        .unwrap();
        db.complete_tile(id, 2).unwrap();
        let failure = TileFailure {
            tile: 1,
            worker: "w".into(),
            error: "boom".into(),
        };
        db.insert_failure(id, &failure, 8).unwrap();
        db.set_job_state(id, JobState::Running, None, Some(6), None)
            .unwrap();
        let jobs = db.load_jobs().unwrap();
        assert_eq!(jobs.len(), 1);
        let j = &jobs[0];
        assert_eq!((j.state, j.started_ms), (JobState::Running, Some(6)));
        assert_eq!(j.tiles_done, vec![2]);
        assert_eq!(j.failures, vec![failure]);
        assert_eq!(j.assets, job().assets);
        // Completing tile 2 dropped its lease; tile 3's is still there.
        let leases = db.load_leases().unwrap();
        assert_eq!(leases.iter().map(|l| l.id).collect::<Vec<_>>(), vec![10]);
    }

    #[test]
    fn epochs_increase() {
        let db = Db::open_in_memory().unwrap();
        assert_eq!(db.next_epoch().unwrap(), 1);
        assert_eq!(db.next_epoch().unwrap(), 2);
    }

    #[test]
    fn migrations_run_once_on_reopen() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.db");
        {
            let mut db = Db::open(&path).unwrap();
            db.insert_job(&job()).unwrap();
        }
        let db = Db::open(&path).unwrap();
        assert_eq!(db.load_jobs().unwrap().len(), 1);
    }
}
