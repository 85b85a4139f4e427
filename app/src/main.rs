use clap::Parser;

fn main() -> std::process::ExitCode {
    let cli = app::cli::Cli::parse();
    match app::cli::run(cli) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
