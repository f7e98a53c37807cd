//! How much memory the server may use: `--max-memory`, else its cgroup's limit (what a container's
//! memory limit becomes), else the machine's memory. Never "unlimited": a budget the server
//! cannot see past is what got it killed.

use std::path::{Path, PathBuf};

/// Bytes in a size such as `96Mi`, `256MiB`, `1G` or `134217728`. The units are binary (K, M, G
/// and T, with or without `i`, `iB` or in lower case, as `podman --memory 96m` and Kubernetes'
/// `96Mi` mean them); `KB`, `MB`, `GB` and `TB` are decimal. Zero, negative and fractional-byte
/// sizes are refused.
pub(crate) fn parse_size(text: &str) -> Result<u64, String> {
    let trimmed = text.trim();
    let split = trimmed
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(trimmed.len());
    let (number, unit) = trimmed.split_at(split);
    let bad = || {
        format!(
            "{text:?} is not a memory size such as 96Mi, 256MiB, 1G or 134217728 (bytes); \
             K, M, G and T are binary units, KB, MB, GB and TB decimal"
        )
    };
    if number.is_empty() {
        return Err(bad());
    }
    let scale: u64 = match unit.trim() {
        "" | "B" | "b" => 1,
        "K" | "k" | "Ki" | "KiB" => 1 << 10,
        "M" | "m" | "Mi" | "MiB" => 1 << 20,
        "G" | "g" | "Gi" | "GiB" => 1 << 30,
        "T" | "t" | "Ti" | "TiB" => 1 << 40,
        "KB" | "kB" => 1_000,
        "MB" => 1_000_000,
        "GB" => 1_000_000_000,
        "TB" => 1_000_000_000_000,
        _ => return Err(bad()),
    };
    let bytes = if number.contains('.') {
        let value: f64 = number.parse().map_err(|_| bad())?;
        let bytes = value * scale as f64;
        if !bytes.is_finite() || bytes >= u64::MAX as f64 {
            return Err(bad());
        }
        bytes.round() as u64
    } else {
        number
            .parse::<u64>()
            .ok()
            .and_then(|n| n.checked_mul(scale))
            .ok_or_else(bad)?
    };
    if bytes == 0 {
        return Err(format!(
            "{text:?}: a memory budget of 0 bytes cannot serve anything; leave the setting out \
             to follow the container's limit"
        ));
    }
    Ok(bytes)
}

/// A size as people read it: `96.0 MiB`.
pub(crate) fn show_size(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut value = bytes as f64;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < UNITS.len() {
        value /= 1024.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{bytes} B")
    } else {
        format!("{value:.1} {}", UNITS[unit])
    }
}

/// Where the total came from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) enum LimitSource {
    /// `--max-memory` or the TOML key `max_memory`.
    Setting,
    /// The cgroup's limit, read from this file.
    Cgroup(PathBuf),
    /// No cgroup limit (or none readable): the machine's memory, with why.
    Machine(String),
}

impl std::fmt::Display for LimitSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LimitSource::Setting => write!(f, "--max-memory"),
            LimitSource::Cgroup(file) => write!(f, "the cgroup's limit ({})", file.display()),
            LimitSource::Machine(why) => write!(f, "the machine's memory ({why})"),
        }
    }
}

/// The memory the server may use in all, and where that figure came from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct MemoryLimit {
    pub(crate) bytes: u64,
    pub(crate) source: LimitSource,
}

/// What a cgroup limit file says.
#[derive(Debug, PartialEq, Eq)]
enum CgroupLimit {
    Bytes(u64),
    /// `max` (v2) or v1's page-rounded i64::MAX: no limit at this level.
    Unlimited,
}

/// v1 writes "no limit" as i64::MAX rounded down to a page; anything this large is none.
const V1_UNLIMITED_FLOOR: u64 = 1 << 62;

fn read_cgroup_limit(file: &Path) -> Result<CgroupLimit, String> {
    let text = std::fs::read_to_string(file)
        .map_err(|e| format!("cannot read {}: {e}", file.display()))?;
    let text = text.trim();
    if text == "max" {
        return Ok(CgroupLimit::Unlimited);
    }
    match text.parse::<u64>() {
        Ok(n) if n >= V1_UNLIMITED_FLOOR => Ok(CgroupLimit::Unlimited),
        Ok(0) => Err(format!("{} says 0 bytes", file.display())),
        Ok(n) => Ok(CgroupLimit::Bytes(n)),
        Err(_) => Err(format!(
            "{} says {text:?}, not a number of bytes or max",
            file.display()
        )),
    }
}

/// The files that may hold this process's memory limit, nearest first: its own cgroup's and
/// each ancestor's (a limit set on a parent binds too), for cgroup v2 and v1, below `root`
/// (`/sys/fs/cgroup`) as `/proc/self/cgroup` (`proc_cgroup`) names them. In a container the
/// cgroup namespace makes its own cgroup `/`, so the root's file is the container's limit.
fn limit_files(root: &Path, proc_cgroup: &str) -> Vec<PathBuf> {
    let mut files = Vec::new();
    for line in proc_cgroup.lines() {
        let mut fields = line.splitn(3, ':');
        let (Some(_), Some(controllers), Some(path)) =
            (fields.next(), fields.next(), fields.next())
        else {
            continue;
        };
        let (base, file) = if controllers.is_empty() {
            (root.to_path_buf(), "memory.max")
        } else if controllers.split(',').any(|c| c == "memory") {
            (root.join("memory"), "memory.limit_in_bytes")
        } else {
            continue;
        };
        let mut dir = Some(Path::new(path.trim_start_matches('/')));
        while let Some(relative) = dir {
            let candidate = base.join(relative).join(file);
            if !files.contains(&candidate) {
                files.push(candidate);
            }
            dir = relative.parent();
        }
    }
    files
}

/// The tightest cgroup limit among `files` that exist; Ok(None) when every one that exists says
/// no limit (or none exists), Err when one exists but cannot be read or makes no sense.
fn tightest_cgroup_limit(files: &[PathBuf]) -> Result<Option<(u64, PathBuf)>, String> {
    let mut tightest: Option<(u64, PathBuf)> = None;
    for file in files.iter().filter(|f| f.exists()) {
        if let CgroupLimit::Bytes(n) = read_cgroup_limit(file)?
            && tightest.as_ref().is_none_or(|(t, _)| n < *t)
        {
            tightest = Some((n, file.clone()));
        }
    }
    Ok(tightest)
}

/// The machine's memory (MemTotal of `/proc/meminfo`).
fn machine_memory(meminfo: &str) -> Option<u64> {
    meminfo
        .lines()
        .find_map(|l| l.strip_prefix("MemTotal:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|kib| kib.parse::<u64>().ok())
        .map(|kib| kib * 1024)
}

/// The memory the server may use: `setting` if given, else the tightest cgroup limit above this
/// process, else the machine's memory. Err only when not even the machine's memory can be read.
pub(crate) fn resolve(setting: Option<u64>) -> anyhow::Result<MemoryLimit> {
    resolve_from(
        setting,
        Path::new("/sys/fs/cgroup"),
        std::fs::read_to_string("/proc/self/cgroup").unwrap_or_default(),
        std::fs::read_to_string("/proc/meminfo").unwrap_or_default(),
    )
}

fn resolve_from(
    setting: Option<u64>,
    cgroup_root: &Path,
    proc_cgroup: String,
    meminfo: String,
) -> anyhow::Result<MemoryLimit> {
    if let Some(bytes) = setting {
        return Ok(MemoryLimit {
            bytes,
            source: LimitSource::Setting,
        });
    }
    let files = limit_files(cgroup_root, &proc_cgroup);
    let why = match tightest_cgroup_limit(&files) {
        Ok(Some((bytes, file))) => {
            return Ok(MemoryLimit {
                bytes,
                source: LimitSource::Cgroup(file),
            });
        }
        Ok(None) if files.iter().any(|f| f.exists()) => "the cgroup sets no memory limit".into(),
        Ok(None) => "no cgroup memory controller found".to_string(),
        Err(e) => format!("the cgroup's limit is unreadable: {e}"),
    };
    let bytes = machine_memory(&meminfo).ok_or_else(|| {
        anyhow::anyhow!(
            "cannot tell how much memory the server may use ({why}, and /proc/meminfo gives no \
             MemTotal): set --max-memory"
        )
    })?;
    Ok(MemoryLimit {
        bytes,
        source: LimitSource::Machine(why),
    })
}

/// This process's resident memory in bytes (VmRSS), if readable.
pub(crate) fn resident_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|kib| kib.parse::<u64>().ok())
        .map(|kib| kib * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_read_as_containers_and_kubernetes_write_them() {
        assert_eq!(parse_size("96m").unwrap(), 96 << 20);
        assert_eq!(parse_size("96Mi").unwrap(), 96 << 20);
        assert_eq!(parse_size("256MiB").unwrap(), 256 << 20);
        assert_eq!(parse_size("1G").unwrap(), 1 << 30);
        assert_eq!(parse_size("1.5Gi").unwrap(), 3 << 29);
        assert_eq!(parse_size("134217728").unwrap(), 128 << 20);
        assert_eq!(parse_size("100MB").unwrap(), 100_000_000);
        for bad in [
            "0",
            "0Mi",
            "-5Mi",
            "lots",
            "",
            "12 parsecs",
            "Mi",
            "1e9",
            "1.2.3M",
        ] {
            assert!(parse_size(bad).is_err(), "{bad:?} was taken");
        }
        assert!(parse_size("0").unwrap_err().contains("0 bytes"));
        assert!(parse_size("99999999999999999999T").is_err());
        assert_eq!(show_size(96 << 20), "96.0 MiB");
        assert_eq!(show_size(512), "512 B");
    }

    fn cgroup_tree(files: &[(&str, &str)]) -> tempfile::TempDir {
        let root = tempfile::tempdir().unwrap();
        for (path, text) in files {
            let file = root.path().join(path);
            std::fs::create_dir_all(file.parent().unwrap()).unwrap();
            std::fs::write(file, text).unwrap();
        }
        root
    }

    const MEMINFO: &str = "MemTotal:       24576000 kB\nMemFree: 1 kB\n";

    #[test]
    fn the_default_is_the_tightest_cgroup_limit_then_the_machine() {
        // v2 in a container: its own cgroup is the namespace's root.
        let root = cgroup_tree(&[("memory.max", "100663296\n")]);
        let limit = resolve_from(None, root.path(), "0::/\n".into(), MEMINFO.into()).unwrap();
        assert_eq!(limit.bytes, 96 << 20);
        assert!(matches!(limit.source, LimitSource::Cgroup(_)));

        // v2 on a host: a parent's limit binds a child that says max.
        let root = cgroup_tree(&[
            ("system.slice/memory.max", "268435456\n"),
            ("system.slice/prac.service/memory.max", "max\n"),
        ]);
        let limit = resolve_from(
            None,
            root.path(),
            "0::/system.slice/prac.service\n".into(),
            MEMINFO.into(),
        )
        .unwrap();
        assert_eq!(limit.bytes, 256 << 20);

        // v1, as podman on a cgroup-v1 host mounts it.
        let root = cgroup_tree(&[("memory/memory.limit_in_bytes", "134217728\n")]);
        let limit = resolve_from(
            None,
            root.path(),
            "4:memory:/libpod_parent/abc\n0::/\n".into(),
            MEMINFO.into(),
        )
        .unwrap();
        assert_eq!(limit.bytes, 128 << 20);

        // No limit anywhere: the machine's memory, never unlimited.
        let root = cgroup_tree(&[
            ("memory.max", "max\n"),
            ("memory/memory.limit_in_bytes", "9223372036854771712\n"),
        ]);
        let limit = resolve_from(
            None,
            root.path(),
            "4:memory:/\n0::/\n".into(),
            MEMINFO.into(),
        )
        .unwrap();
        assert_eq!(limit.bytes, 24576000 * 1024);
        assert!(
            matches!(limit.source, LimitSource::Machine(ref why) if why.contains("no memory limit"))
        );

        // An unreadable or nonsensical file: the machine's memory, and the log says why.
        let root = cgroup_tree(&[("memory.max", "plenty\n")]);
        let limit = resolve_from(None, root.path(), "0::/\n".into(), MEMINFO.into()).unwrap();
        assert!(matches!(limit.source, LimitSource::Machine(ref why) if why.contains("plenty")));

        // Nothing readable at all: an error that names the flag.
        let root = cgroup_tree(&[]);
        let err = resolve_from(None, root.path(), String::new(), String::new()).unwrap_err();
        assert!(err.to_string().contains("--max-memory"), "{err}");

        // The setting wins.
        let limit =
            resolve_from(Some(42 << 20), root.path(), String::new(), String::new()).unwrap();
        assert_eq!(
            (limit.bytes, limit.source),
            (42 << 20, LimitSource::Setting)
        );
    }
}
