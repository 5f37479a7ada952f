fn main() {
    eprintln!("spidar: no commands yet");
    std::process::exit(2);
}
