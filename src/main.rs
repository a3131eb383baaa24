#![forbid(unsafe_code)]

use clap::Parser;

/// Large buffers on transparent huge pages (see `rall::memory`).
#[global_allocator]
static ALLOCATOR: rall::memory::HugePageAlloc = rall::memory::HugePageAlloc;

/// `rall ... | head` closes our stdout early: stop quietly, as a shell tool does (exit
/// status 141 = killed by SIGPIPE), instead of panicking in `println!`.
fn quiet_on_closed_stdout() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let msg = info
            .payload()
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| info.payload().downcast_ref::<&str>().copied())
            .unwrap_or("");
        if msg.starts_with("failed printing to stdout") && msg.contains("Broken pipe") {
            std::process::exit(141);
        }
        default(info)
    }));
}

fn main() -> std::process::ExitCode {
    quiet_on_closed_stdout();
    let cli = rall::cli::Cli::parse();
    match rall::cli::run(cli) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
