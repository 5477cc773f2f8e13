//! SQLite: jobs, their assets, finished tiles, tile failures, live leases and registered
//! workers. Numbered migrations run at start-up. One connection, in WAL mode, locked
//! exclusively so a second coordinator cannot open the same data dir.
//!
//! The farm's transitions each call one method here, and each method is one savepoint: a
//! transition is either stored whole or not at all (and then the farm's memory is untouched).
//!
//! Group commit: transitions run inside one open transaction, and [`Db::commit`] commits all
//! of them at once. The farm answers a request only after the commit that holds its
//! transition (see `Farm::sync`), so many requests share one commit (a few WAL pages instead
//! of a few per request). Transitions that take an id from SQLite (jobs, workers) commit on
//! their own, after the pending ones, so a failed commit can never hand an id out twice.
//!
//! Durability: `synchronous=NORMAL` survives a killed process (the kill -9 test) but may lose
//! the last transactions on power loss; finished tiles then render again, nothing breaks.

use std::path::Path;

use protocol::{BundleFile, JobSpec, JobState, PassInfo, TileFailure};
use rusqlite::{params, Connection, OptionalExtension};

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
    // 2: coordinator-issued worker identities; leases and failures name the worker by id.
    "CREATE TABLE workers (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        name TEXT NOT NULL,
        registered_ms INTEGER NOT NULL
    );
    ALTER TABLE leases ADD COLUMN worker_id INTEGER NOT NULL DEFAULT 0;
    ALTER TABLE tile_failures ADD COLUMN worker_id INTEGER NOT NULL DEFAULT 0;",
    // 3: the finished passes of progressive jobs (their sums live in the job's sums file).
    "CREATE TABLE passes (
        job_id INTEGER NOT NULL,
        pass INTEGER NOT NULL,
        wall_s REAL NOT NULL,
        spp_mean REAL NOT NULL,
        error REAL NOT NULL,
        active_blocks INTEGER NOT NULL,
        PRIMARY KEY (job_id, pass)
    ) WITHOUT ROWID;",
];

pub struct Db {
    conn: Connection,
    /// A batch transaction is open.
    open: bool,
    /// Transitions stored so far (committed or in the open batch).
    written: u64,
    /// Transitions covered by a commit that succeeded.
    committed: u64,
    /// The latest batch whose commit failed, as (first, last) transition numbers.
    lost: Option<(u64, u64)>,
}

/// Whether a transition is stored for good.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Durable {
    Yes,
    /// Its batch's commit failed: it is not stored.
    Lost,
}

/// A jobs row as SQLite returns it, before its JSON and state are parsed.
struct JobColumns {
    name: String,
    scene_file: String,
    scene_hash: String,
    spec: String,
    state: String,
    error: Option<String>,
    created_ms: i64,
    started_ms: Option<i64>,
    finished_ms: Option<i64>,
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

/// A job row that cannot be resumed, and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UnloadableJob {
    pub id: u64,
    pub name: String,
    pub scene_file: String,
    pub created_ms: u64,
    pub reason: String,
}

/// One row of the jobs table as read back.
#[derive(Clone, Debug)]
pub enum LoadedJob {
    Ok(Box<StoredJob>),
    Unloadable(UnloadableJob),
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StoredLease {
    pub id: u64,
    pub job_id: u64,
    pub tile: u32,
    /// The worker's label, kept for logs.
    pub worker: String,
    pub worker_id: u64,
    pub granted_ms: u64,
}

/// A job's row after it ends or changes state.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct JobRow {
    pub state: JobState,
    pub error: Option<String>,
    pub started_ms: Option<u64>,
    pub finished_ms: Option<u64>,
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StoredWorker {
    pub id: u64,
    pub name: String,
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
        // Every pending step in one transaction: the upgrade happens whole or not at all, and
        // a new database (the embedded farm's, at every start) commits its schema once.
        if version < MIGRATIONS.len() {
            let tx = conn.transaction()?;
            for sql in &MIGRATIONS[version..] {
                tx.execute_batch(sql)?;
            }
            tx.pragma_update(None, "user_version", MIGRATIONS.len() as i64)?;
            tx.commit()?;
        }
        Ok(Db {
            conn,
            open: false,
            written: 0,
            committed: 0,
            lost: None,
        })
    }

    /// Runs one transition's statements in the open batch (opening it if need be), as a
    /// savepoint: on error nothing of it stays.
    fn transition<T>(
        &mut self,
        statements: impl FnOnce(&Connection) -> Result<T, StoreError>,
    ) -> Result<T, StoreError> {
        if !self.open {
            self.conn.execute_batch("BEGIN")?;
            self.open = true;
        }
        self.conn.execute_batch("SAVEPOINT transition")?;
        match statements(&self.conn) {
            Ok(value) => {
                self.conn.execute_batch("RELEASE transition")?;
                self.written += 1;
                Ok(value)
            }
            Err(e) => {
                if self
                    .conn
                    .execute_batch("ROLLBACK TO transition; RELEASE transition")
                    .is_err()
                {
                    // The savepoint cannot be undone alone: the whole batch goes.
                    self.abandon();
                }
                Err(e)
            }
        }
    }

    /// Drops the open batch: its transitions are lost.
    fn abandon(&mut self) {
        let _ = self.conn.execute_batch("ROLLBACK");
        self.open = false;
        if self.written > self.committed {
            self.lost = Some((self.committed + 1, self.written));
        }
        self.committed = self.written;
    }

    /// The number of the latest transition stored.
    pub fn written(&self) -> u64 {
        self.written
    }

    /// The latest transition committed (lost ones included) and the latest lost batch.
    pub fn committed(&self) -> (u64, Option<(u64, u64)>) {
        (self.committed, self.lost)
    }

    /// Commits the open batch, if any. On failure every transition in it is lost (and
    /// [`Db::durable`] says so).
    pub fn commit(&mut self) -> Result<(), StoreError> {
        if !self.open {
            return Ok(());
        }
        match self.conn.execute_batch("COMMIT") {
            Ok(()) => {
                self.open = false;
                self.committed = self.written;
                Ok(())
            }
            Err(e) => {
                self.abandon();
                Err(e.into())
            }
        }
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
        self.commit()?;
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
        self.written += 1;
        self.committed = self.written;
        Ok(id)
    }

    fn update_job(conn: &Connection, id: u64, row: &JobRow) -> Result<(), StoreError> {
        conn.prepare_cached(
            "UPDATE jobs SET state = ?2, error = ?3, started_ms = ?4, finished_ms = ?5
             WHERE id = ?1",
        )?
        .execute(params![
            id as i64,
            row.state.as_str(),
            row.error,
            row.started_ms.map(|v| v as i64),
            row.finished_ms.map(|v| v as i64)
        ])?;
        Ok(())
    }

    /// A job's new state alone (done after assembly, failed on resume).
    pub fn set_job_state(&mut self, id: u64, row: &JobRow) -> Result<(), StoreError> {
        self.transition(|conn| Self::update_job(conn, id, row))
    }

    fn insert_lease_row(conn: &Connection, lease: &StoredLease) -> Result<(), StoreError> {
        conn.prepare_cached(
            "INSERT INTO leases (id, job_id, tile, worker, worker_id, granted_ms)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
        )?
        .execute(params![
            lease.id as i64,
            lease.job_id as i64,
            lease.tile,
            lease.worker,
            lease.worker_id as i64,
            lease.granted_ms as i64
        ])?;
        Ok(())
    }

    /// A lease, and the job's start when it is the job's first.
    pub fn grant_lease(
        &mut self,
        lease: &StoredLease,
        job_started: Option<&JobRow>,
    ) -> Result<(), StoreError> {
        self.transition(|tx| {
            Self::insert_lease_row(tx, lease)?;
            if let Some(row) = job_started {
                Self::update_job(tx, lease.job_id, row)?;
            }
            Ok(())
        })
    }

    /// Ends leases without finishing their tiles (handed back, expired).
    pub fn end_leases(&mut self, ids: &[u64]) -> Result<(), StoreError> {
        self.transition(|tx| {
            for id in ids {
                tx.prepare_cached("DELETE FROM leases WHERE id = ?1")?
                    .execute([*id as i64])?;
            }
            Ok(())
        })
    }

    /// Records a finished tile and drops every lease on it.
    pub fn complete_tile(&mut self, job_id: u64, tile: u32) -> Result<(), StoreError> {
        self.transition(|tx| {
            tx.prepare_cached("INSERT OR IGNORE INTO tiles_done (job_id, tile) VALUES (?1, ?2)")?
                .execute(params![job_id as i64, tile])?;
            tx.prepare_cached("DELETE FROM leases WHERE job_id = ?1 AND tile = ?2")?
                .execute(params![job_id as i64, tile])?;
            Ok(())
        })
    }

    /// Records a finished pass of a progressive job; the tiles it finished start over in the
    /// next pass, so their rows go.
    pub fn record_pass(&mut self, job_id: u64, pass: &PassInfo) -> Result<(), StoreError> {
        self.transition(|tx| {
            tx.prepare_cached(
                "INSERT OR REPLACE INTO passes (job_id, pass, wall_s, spp_mean, error, \
                 active_blocks) VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            )?
            .execute(params![
                job_id as i64,
                pass.pass,
                pass.wall_s,
                pass.spp_mean,
                // SQLite stores no infinity: an unknown error is stored as -1.
                if pass.error.is_finite() {
                    pass.error
                } else {
                    -1.0
                },
                pass.active_blocks
            ])?;
            tx.prepare_cached("DELETE FROM tiles_done WHERE job_id = ?1")?
                .execute([job_id as i64])?;
            Ok(())
        })
    }

    /// A progressive job's finished passes, in order.
    pub fn load_passes(&self, job_id: u64) -> Result<Vec<PassInfo>, StoreError> {
        let mut stmt = self.conn.prepare_cached(
            "SELECT pass, wall_s, spp_mean, error, active_blocks FROM passes \
             WHERE job_id = ?1 ORDER BY pass",
        )?;
        let rows = stmt.query_map([job_id as i64], |r| {
            let error: f64 = r.get(3)?;
            Ok(PassInfo {
                pass: r.get(0)?,
                wall_s: r.get(1)?,
                spp_mean: r.get(2)?,
                error: if error < 0.0 { f64::INFINITY } else { error },
                active_blocks: r.get(4)?,
            })
        })?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    fn end_job(conn: &Connection, job_id: u64, row: &JobRow) -> Result<(), StoreError> {
        conn.prepare_cached("DELETE FROM leases WHERE job_id = ?1")?
            .execute([job_id as i64])?;
        Self::update_job(conn, job_id, row)
    }

    /// A failed tile: its lease ends, the failure is kept, and `job_end` (when the failure
    /// is fatal) ends the job and every lease on it.
    pub fn record_failure(
        &mut self,
        lease_id: u64,
        job_id: u64,
        failure: &TileFailure,
        at_ms: u64,
        job_end: Option<&JobRow>,
    ) -> Result<(), StoreError> {
        self.transition(|tx| {
            tx.prepare_cached("DELETE FROM leases WHERE id = ?1")?
                .execute([lease_id as i64])?;
            tx.prepare_cached(
                "INSERT INTO tile_failures (job_id, tile, worker, worker_id, error, at_ms)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            )?
            .execute(params![
                job_id as i64,
                failure.tile,
                failure.worker,
                failure.worker_id as i64,
                failure.error,
                at_ms as i64
            ])?;
            if let Some(row) = job_end {
                Self::end_job(tx, job_id, row)?;
            }
            Ok(())
        })
    }

    /// A job ends (cancelled, failed): its leases go with it.
    pub fn finish_job(&mut self, job_id: u64, row: &JobRow) -> Result<(), StoreError> {
        self.transition(|tx| Self::end_job(tx, job_id, row))
    }

    /// A failed job runs again with fresh failure counts.
    pub fn retry_job(&mut self, job_id: u64, row: &JobRow) -> Result<(), StoreError> {
        self.transition(|tx| {
            tx.prepare_cached("DELETE FROM tile_failures WHERE job_id = ?1")?
                .execute([job_id as i64])?;
            Self::update_job(tx, job_id, row)
        })
    }

    /// Issues a new worker id (never reused, even after [`Db::forget_worker`]).
    /// Commits at once, with whatever is pending: an id handed out is never rolled back.
    pub fn register_worker(&mut self, name: &str, at_ms: u64) -> Result<u64, StoreError> {
        let id = self.transition(|conn| {
            conn.prepare_cached("INSERT INTO workers (name, registered_ms) VALUES (?1, ?2)")?
                .execute(params![name, at_ms as i64])?;
            Ok(conn.last_insert_rowid() as u64)
        })?;
        self.commit()?;
        Ok(id)
    }

    pub fn forget_worker(&mut self, id: u64) -> Result<(), StoreError> {
        self.transition(|conn| {
            conn.prepare_cached("DELETE FROM workers WHERE id = ?1")?
                .execute([id as i64])?;
            Ok(())
        })
    }

    pub fn load_workers(&self) -> Result<Vec<StoredWorker>, StoreError> {
        let mut stmt = self
            .conn
            .prepare("SELECT id, name FROM workers ORDER BY id")?;
        let rows = stmt.query_map([], |r| {
            Ok(StoredWorker {
                id: r.get::<_, i64>(0)? as u64,
                name: r.get(1)?,
            })
        })?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    /// Makes every later write fail, as a full disk or a read-only file would: tests use it
    /// to show that a failed write leaves the farm's state untouched.
    #[cfg(test)]
    pub fn fail_writes(&self, fail: bool) {
        self.conn
            .pragma_update(None, "query_only", fail)
            .expect("query_only is a plain pragma");
    }

    /// Runs raw SQL, for tests that plant rows a coordinator cannot load.
    #[cfg(test)]
    pub fn execute_for_tests(&self, sql: &str) {
        self.conn.execute_batch(sql).unwrap();
    }

    /// Every job, oldest first, with finished tiles and failures. A row that cannot be read
    /// back (settings that no longer parse, an unknown state...) is returned as
    /// [`LoadedJob::Unloadable`] with the reason, so one bad row never stops a start-up.
    pub fn load_jobs(&self) -> Result<Vec<LoadedJob>, StoreError> {
        let mut stmt = self.conn.prepare(
            "SELECT id, name, scene_file, scene_hash, spec, state, error, created_ms,
                    started_ms, finished_ms
             FROM jobs ORDER BY id",
        )?;
        let rows = stmt.query_map([], |r| {
            let id = r.get::<_, i64>(0)? as u64;
            let row = (|| -> rusqlite::Result<JobColumns> {
                Ok(JobColumns {
                    name: r.get(1)?,
                    scene_file: r.get(2)?,
                    scene_hash: r.get(3)?,
                    spec: r.get(4)?,
                    state: r.get(5)?,
                    error: r.get(6)?,
                    created_ms: r.get(7)?,
                    started_ms: r.get(8)?,
                    finished_ms: r.get(9)?,
                })
            })();
            let label = |i| r.get::<_, String>(i).unwrap_or_default();
            let created = r.get::<_, i64>(7).unwrap_or(0).max(0) as u64;
            Ok((id, row, (label(1), label(2), created)))
        })?;
        let mut jobs = Vec::new();
        for row in rows {
            let (id, row, (name, scene_file, created_ms)) = row?;
            let loaded = row
                .map_err(|e| format!("its row does not read back: {e}"))
                .and_then(|row| self.stored_job(id, row).map_err(|e| e.to_string()));
            jobs.push(match loaded {
                Ok(job) => LoadedJob::Ok(Box::new(job)),
                Err(reason) => LoadedJob::Unloadable(UnloadableJob {
                    id,
                    name,
                    scene_file,
                    created_ms,
                    reason,
                }),
            });
        }
        Ok(jobs)
    }

    fn stored_job(&self, id: u64, c: JobColumns) -> Result<StoredJob, StoreError> {
        let spec: JobSpec = serde_json::from_str(&c.spec)
            .map_err(|e| StoreError::Corrupt(format!("its settings do not parse: {e}")))?;
        let state = JobState::parse(&c.state)
            .ok_or_else(|| StoreError::Corrupt(format!("its state {:?} is unknown", c.state)))?;
        Ok(StoredJob {
            id,
            name: c.name,
            scene_file: c.scene_file,
            scene_hash: c.scene_hash,
            spec,
            state,
            error: c.error,
            created_ms: c.created_ms.max(0) as u64,
            started_ms: c.started_ms.map(|v| v.max(0) as u64),
            finished_ms: c.finished_ms.map(|v| v.max(0) as u64),
            assets: self.job_assets(id)?,
            tiles_done: self.tiles_done(id)?,
            failures: self.failures(id)?,
        })
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
            "SELECT tile, worker, worker_id, error FROM tile_failures WHERE job_id = ?1
             ORDER BY rowid",
        )?;
        let rows = stmt.query_map([job_id as i64], |r| {
            Ok(TileFailure {
                tile: r.get(0)?,
                worker: r.get(1)?,
                worker_id: r.get::<_, i64>(2)? as u64,
                error: r.get(3)?,
            })
        })?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    pub fn load_leases(&self) -> Result<Vec<StoredLease>, StoreError> {
        let mut stmt = self.conn.prepare(
            "SELECT id, job_id, tile, worker, worker_id, granted_ms FROM leases ORDER BY id",
        )?;
        let rows = stmt.query_map([], |r| {
            Ok(StoredLease {
                id: r.get::<_, i64>(0)? as u64,
                job_id: r.get::<_, i64>(1)? as u64,
                tile: r.get(2)?,
                worker: r.get(3)?,
                worker_id: r.get::<_, i64>(4)? as u64,
                granted_ms: r.get::<_, i64>(5)? as u64,
            })
        })?;
        // A row that does not read back is dropped: a lease is only an optimisation.
        Ok(rows.filter_map(Result::ok).collect())
    }
}

impl Drop for Db {
    /// A clean close keeps what is pending (a killed process loses only unanswered requests).
    fn drop(&mut self) {
        if let Err(e) = self.commit() {
            tracing::error!("the last writes could not be committed: {e}");
        }
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

    fn lease(id: u64, job_id: u64, tile: u32) -> StoredLease {
        StoredLease {
            id,
            job_id,
            tile,
            worker: "w".into(),
            worker_id: 1,
            granted_ms: 7,
        }
    }

    fn running() -> JobRow {
        JobRow {
            state: JobState::Running,
            error: None,
            started_ms: Some(6),
            finished_ms: None,
        }
    }

    #[test]
    fn a_job_round_trips_with_its_progress() {
        let mut db = Db::open_in_memory().unwrap();
        let id = db.insert_job(&job()).unwrap();
        db.grant_lease(&lease(9, id, 2), Some(&running())).unwrap();
        db.grant_lease(&lease(10, id, 3), None).unwrap();
        db.grant_lease(&lease(11, id, 1), None).unwrap();
        db.complete_tile(id, 2).unwrap();
        let failure = TileFailure {
            tile: 1,
            worker: "w".into(),
            worker_id: 1,
            error: "boom".into(),
        };
        db.record_failure(11, id, &failure, 8, None).unwrap();
        let jobs = db.load_jobs().unwrap();
        assert_eq!(jobs.len(), 1);
        let LoadedJob::Ok(j) = &jobs[0] else {
            panic!("{:?}", jobs[0])
        };
        assert_eq!((j.state, j.started_ms), (JobState::Running, Some(6)));
        assert_eq!(j.tiles_done, vec![2]);
        assert_eq!(j.failures, vec![failure]);
        assert_eq!(j.assets, job().assets);
        // Completing tile 2 and failing tile 1 dropped their leases; tile 3's is still there.
        let leases = db.load_leases().unwrap();
        assert_eq!(leases.iter().map(|l| l.id).collect::<Vec<_>>(), vec![10]);
    }

    #[test]
    fn a_failed_write_stores_nothing_of_the_transition() {
        let mut db = Db::open_in_memory().unwrap();
        let id = db.insert_job(&job()).unwrap();
        db.fail_writes(true);
        assert!(db.grant_lease(&lease(9, id, 2), Some(&running())).is_err());
        db.fail_writes(false);
        assert!(db.load_leases().unwrap().is_empty());
        let LoadedJob::Ok(j) = &db.load_jobs().unwrap()[0] else {
            panic!()
        };
        assert_eq!(j.state, JobState::Queued);
    }

    #[test]
    fn a_row_that_does_not_parse_is_reported_not_fatal() {
        let mut db = Db::open_in_memory().unwrap();
        let good = db.insert_job(&job()).unwrap();
        let bad = db.insert_job(&job()).unwrap();
        db.execute_for_tests(&format!(
            "UPDATE jobs SET spec = '{{not json' WHERE id = {bad}"
        ));
        let jobs = db.load_jobs().unwrap();
        assert!(matches!(&jobs[0], LoadedJob::Ok(j) if j.id == good));
        match &jobs[1] {
            LoadedJob::Unloadable(u) => {
                assert_eq!((u.id, u.name.as_str()), (bad, "a"));
                assert!(u.reason.contains("settings"), "{}", u.reason);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn worker_ids_are_never_reused() {
        let mut db = Db::open_in_memory().unwrap();
        let a = db.register_worker("w", 1).unwrap();
        let b = db.register_worker("w", 1).unwrap();
        assert_ne!(a, b);
        db.forget_worker(b).unwrap();
        let c = db.register_worker("w", 1).unwrap();
        assert!(c > b);
        let ids: Vec<u64> = db.load_workers().unwrap().iter().map(|w| w.id).collect();
        assert_eq!(ids, [a, c]);
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
