//! `cargo xtask mesh info | convert | generate`.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use deform_mesh::generate::{BoxGrid, Split};
use deform_mesh::io::{self, MshFormat, MshVersion};
use deform_mesh::{MeshInfo, MeshOptions, TetMesh};

#[derive(Debug, Subcommand)]
pub enum MeshTask {
    /// Counts, volume, bounding box, quality and surface statistics of a mesh file.
    Info {
        /// A .msh, .node or .ele file.
        file: PathBuf,
    },
    /// Converts between formats, chosen by extension (.msh, .node/.ele, .vtu, .obj).
    Convert {
        /// Input mesh (.msh, .node, .ele).
        input: PathBuf,
        /// Output file.
        output: PathBuf,
        #[command(flatten)]
        msh: MshArgs,
    },
    /// Writes a structured mesh.
    Generate {
        /// What to generate.
        #[arg(value_enum)]
        shape: Shape,
        /// Cells along x, y, z, e.g. 20x4x4.
        #[arg(long, value_parser = parse_triple::<usize>)]
        cells: Option<[usize; 3]>,
        /// Edge lengths, e.g. 1x0.25x0.25 (beam: cubic cells along a unit length; box: 1x1x1).
        #[arg(long, value_parser = parse_triple::<f64>)]
        size: Option<[f64; 3]>,
        /// Tets per cube: 5 or 6.
        #[arg(long, value_enum, default_value = "6")]
        split: SplitArg,
        /// Output file (.msh, .node/.ele, .vtu, .obj).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        msh: MshArgs,
    },
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum Shape {
    /// A cantilever beam (default 16x4x4 cells of cubes with total length 1).
    Beam,
    /// A box (default 4x4x4 cells on the unit cube).
    Box,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum SplitArg {
    #[value(name = "5")]
    Five,
    #[value(name = "6")]
    Six,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum VersionArg {
    #[value(name = "2.2")]
    V2_2,
    #[value(name = "4.1")]
    V4_1,
}

#[derive(Debug, Args)]
pub struct MshArgs {
    /// Gmsh format version for .msh output.
    #[arg(long, value_enum, default_value = "4.1")]
    msh_version: VersionArg,
    /// Write .msh as binary.
    #[arg(long)]
    binary: bool,
}

fn parse_triple<T: std::str::FromStr>(s: &str) -> Result<[T; 3], String> {
    let parts: Vec<&str> = s.split('x').collect();
    let [a, b, c] = parts.as_slice() else {
        return Err(format!("expected AxBxC, got {s:?}"));
    };
    let p = |v: &str| {
        v.trim()
            .parse::<T>()
            .map_err(|_| format!("{v:?} is not a number"))
    };
    Ok([p(a)?, p(b)?, p(c)?])
}

pub fn run(task: MeshTask) -> Result<()> {
    match task {
        MeshTask::Info { file } => {
            let mesh = io::read(&file, &MeshOptions::default())?;
            print!(
                "file            {}\n{}",
                file.display(),
                MeshInfo::of(&mesh)
            );
            Ok(())
        }
        MeshTask::Convert { input, output, msh } => {
            write(&output, &io::read(&input, &MeshOptions::default())?, &msh)
        }
        MeshTask::Generate {
            shape,
            cells,
            size,
            split,
            out,
            msh,
        } => {
            let split = match split {
                SplitArg::Five => Split::Five,
                SplitArg::Six => Split::Six,
            };
            let cells = cells.unwrap_or(match shape {
                Shape::Beam => [16, 4, 4],
                Shape::Box => [4, 4, 4],
            });
            // A beam of cubes along a unit length; a unit box.
            let size = size.unwrap_or(match shape {
                Shape::Beam => cells.map(|c| c as f64 / cells[0] as f64),
                Shape::Box => [1.0; 3],
            });
            let grid = BoxGrid::new(cells, size).split(split);
            write(&out, &grid.build().context("invalid grid")?, &msh)
        }
    }
}

/// Writes `mesh` by `path`'s extension and says so.
fn write(path: &Path, mesh: &TetMesh, msh: &MshArgs) -> Result<()> {
    if path.extension().and_then(|e| e.to_str()) == Some("msh") {
        let version = match msh.msh_version {
            VersionArg::V2_2 => MshVersion::V2_2,
            VersionArg::V4_1 => MshVersion::V4_1,
        };
        io::write_msh(
            path,
            mesh,
            MshFormat {
                version,
                binary: msh.binary,
            },
        )?;
    } else {
        io::write(path, mesh)?;
    }
    let (v, t) = (mesh.num_vertices(), mesh.num_tets());
    println!("wrote {} ({v} vertices, {t} tets)", path.display());
    Ok(())
}
