//! Flags from a TOML file (`--config farm.toml`). Each key of the command's table (`[serve]`
//! or `[worker]`) stands for the flag of the same name (`max-spp` or `max_spp`) and is used
//! only where neither the command line nor the environment set that flag: flag > env > file
//! > default. The values become ordinary flags, so clap parses and checks them like typed ones.

use std::ffi::OsString;
use std::path::Path;

use clap::parser::ValueSource;
use clap::{ArgMatches, Command};

/// The tables a farm file may hold, one per command, so one file can serve both.
pub const SECTIONS: &[&str] = &["serve", "worker"];

/// The id of the `--config PATH` flag a command must declare to take a file.
pub const CONFIG_ARG: &str = "config";

/// `argv` with the flags that the file named by `--config` (or its environment variable)
/// supplies for the command at `path` (subcommand names from the top; empty for the top
/// level), reading its table `section`. `argv` comes back unchanged when it does not parse
/// or names no file: the real parse then reports what is wrong.
pub fn with_file_flags(
    command: &Command,
    argv: Vec<OsString>,
    path: &[&str],
    section: &str,
) -> Result<Vec<OsString>, String> {
    // Flags the file may supply are not required yet.
    let Ok(matches) = lenient(command.clone()).try_get_matches_from(&argv) else {
        return Ok(argv);
    };
    let mut command = command;
    let mut matches = &matches;
    for name in path {
        match (
            command.find_subcommand(name),
            matches.subcommand_matches(name),
        ) {
            (Some(c), Some(m)) => (command, matches) = (c, m),
            _ => return Ok(argv),
        }
    }
    let Some(file) = matches.get_one::<std::path::PathBuf>(CONFIG_ARG) else {
        return Ok(argv);
    };
    let text = std::fs::read_to_string(file)
        .map_err(|e| format!("cannot read {}: {e}", file.display()))?;
    let extra = file_flags(command, matches, &text, file, section)?;
    Ok(argv.into_iter().chain(extra).collect())
}

fn lenient(command: Command) -> Command {
    let mut command = command.mut_args(|a| a.required(false));
    let names: Vec<String> = command
        .get_subcommands()
        .map(|s| s.get_name().to_string())
        .collect();
    for name in names {
        command = command.mut_subcommand(name, lenient);
    }
    command
}

/// The flags `text`'s table `section` supplies for `command`, skipping those `matches` has
/// from the command line or the environment. Any key that is not one of the command's flags,
/// and any table other than [`SECTIONS`], is an error naming it and `file`.
pub fn file_flags(
    command: &Command,
    matches: &ArgMatches,
    text: &str,
    file: &Path,
    section: &str,
) -> Result<Vec<OsString>, String> {
    let file = file.display();
    let root: toml::Table = toml::from_str(text).map_err(|e| format!("{file}: {e}"))?;
    let mut table = None;
    for (key, value) in &root {
        if !SECTIONS.contains(&key.as_str()) {
            return Err(format!(
                "{file}: unknown key `{key}` (the file holds tables {})",
                SECTIONS
                    .iter()
                    .map(|s| format!("[{s}]"))
                    .collect::<Vec<_>>()
                    .join(" and ")
            ));
        }
        if key == section {
            table = Some(
                value
                    .as_table()
                    .ok_or_else(|| format!("{file}: `{key}` must be a table ([{key}])"))?,
            );
        }
    }
    let mut flags = Vec::new();
    for (key, value) in table.into_iter().flatten() {
        let long = key.replace('_', "-");
        let arg = command
            .get_arguments()
            .find(|a| a.get_long() == Some(long.as_str()) && long != CONFIG_ARG)
            .ok_or_else(|| format!("{file}: unknown key `{key}` in [{section}]"))?;
        let id = arg.get_id().as_str();
        if matches!(
            matches.value_source(id),
            Some(ValueSource::CommandLine | ValueSource::EnvVariable)
        ) {
            continue;
        }
        let takes_value = arg.get_action().takes_values();
        match value {
            toml::Value::Boolean(on) if !takes_value => {
                if *on {
                    flags.push(format!("--{long}").into());
                }
            }
            _ if !takes_value => {
                return Err(format!("{file}: [{section}] {key} must be true or false"))
            }
            toml::Value::String(s) => flags.push(format!("--{long}={s}").into()),
            toml::Value::Integer(n) => flags.push(format!("--{long}={n}").into()),
            toml::Value::Float(x) => flags.push(format!("--{long}={x}").into()),
            _ => {
                return Err(format!(
                    "{file}: [{section}] {key} must be a string or a number"
                ))
            }
        }
    }
    Ok(flags)
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::{Arg, ArgAction};

    fn command() -> Command {
        Command::new("worker")
            .arg(
                Arg::new("coordinator")
                    .long("coordinator")
                    .env("TEST_CF_COORDINATOR")
                    .required(true),
            )
            .arg(
                Arg::new("max_backoff")
                    .long("max-backoff")
                    .env("TEST_CF_MAX_BACKOFF")
                    .value_parser(clap::value_parser!(f64))
                    .default_value("5"),
            )
            .arg(Arg::new("quiet").long("quiet").action(ArgAction::SetTrue))
            .arg(
                Arg::new(CONFIG_ARG)
                    .long("config")
                    .value_parser(clap::value_parser!(std::path::PathBuf)),
            )
    }

    /// The final parse of `argv` with `file` as the config file: (coordinator, max_backoff, quiet).
    fn parse(argv: &[&str], file: &str) -> Result<(String, f64, bool), String> {
        static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let path = std::env::temp_dir().join(format!("tessera-cf-{}-{n}.toml", std::process::id()));
        std::fs::write(&path, file).unwrap();
        let mut argv: Vec<OsString> = argv.iter().map(OsString::from).collect();
        argv.push("--config".into());
        argv.push(path.clone().into());
        let argv = with_file_flags(&command(), argv, &[], "worker");
        let _ = std::fs::remove_file(&path);
        let m = command()
            .try_get_matches_from(argv?)
            .map_err(|e| e.to_string())?;
        Ok((
            m.get_one::<String>("coordinator").unwrap().clone(),
            *m.get_one::<f64>("max_backoff").unwrap(),
            m.get_flag("quiet"),
        ))
    }

    /// Held by the tests that set a variable of [`command`] or read a default it could change.
    static ENV: std::sync::Mutex<()> = std::sync::Mutex::new(());

    #[test]
    fn the_file_fills_what_flags_leave_and_defaults_remain() {
        let _env = ENV.lock().unwrap_or_else(|e| e.into_inner());
        let file =
            "[worker]\ncoordinator = \"http://file:1\"\nquiet = true\n[serve]\nlisten = \"x\"\n";
        let (url, backoff, quiet) = parse(&["worker"], file).unwrap();
        assert_eq!((url.as_str(), backoff, quiet), ("http://file:1", 5.0, true));
        // Keys may be written with underscores; integers fill float flags.
        let (_, backoff, _) = parse(
            &["worker"],
            "[worker]\ncoordinator = \"u\"\nmax_backoff = 2\n",
        )
        .unwrap();
        assert_eq!(backoff, 2.0);
    }

    #[test]
    fn a_flag_beats_the_environment_which_beats_the_file() {
        let file = "[worker]\ncoordinator = \"http://file:1\"\nmax-backoff = 0.5\n";
        let _env = ENV.lock().unwrap_or_else(|e| e.into_inner());
        std::env::set_var("TEST_CF_MAX_BACKOFF", "1.5");
        let from_env = parse(&["worker"], file);
        let from_flag = parse(
            &[
                "worker",
                "--max-backoff",
                "3",
                "--coordinator",
                "http://flag:1",
            ],
            file,
        );
        std::env::remove_var("TEST_CF_MAX_BACKOFF");
        let (url, backoff, _) = from_env.unwrap();
        assert_eq!((url.as_str(), backoff), ("http://file:1", 1.5));
        let (url, backoff, _) = from_flag.unwrap();
        assert_eq!((url.as_str(), backoff), ("http://flag:1", 3.0));
    }

    #[test]
    fn unknown_keys_and_bad_values_name_the_key_and_the_file() {
        let _env = ENV.lock().unwrap_or_else(|e| e.into_inner());
        let err = parse(&["worker"], "[worker]\ncoordinatr = \"u\"\n").unwrap_err();
        assert!(
            err.contains("unknown key `coordinatr` in [worker]"),
            "{err}"
        );
        assert!(err.contains(".toml"), "{err}");
        let err = parse(&["worker"], "[workers]\n").unwrap_err();
        assert!(err.contains("unknown key `workers`"), "{err}");
        let err = parse(&["worker"], "[worker]\nquiet = \"yes\"\n").unwrap_err();
        assert!(err.contains("quiet must be true or false"), "{err}");
        let err = parse(&["worker"], "[worker]\nconfig = \"other.toml\"\n").unwrap_err();
        assert!(err.contains("unknown key `config`"), "{err}");
        let err = parse(&["worker"], "[worker\n").unwrap_err();
        assert!(err.contains(".toml"), "{err}");
        // A value clap refuses is refused as if it were a flag.
        let err = parse(
            &["worker"],
            "[worker]\ncoordinator = \"u\"\nmax-backoff = \"soon\"\n",
        )
        .unwrap_err();
        assert!(err.contains("soon"), "{err}");
    }
}
