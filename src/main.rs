#![forbid(unsafe_code)]

use clap::Parser;

/// Large buffers on transparent huge pages (see `rall::memory`).
#[global_allocator]
static ALLOCATOR: rall::memory::HugePageAlloc = rall::memory::HugePageAlloc;

fn main() -> std::process::ExitCode {
    let cli = rall::cli::Cli::parse();
    match rall::cli::run(cli) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
