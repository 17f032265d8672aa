//! `lungmotion` command line: a thin shell over the library.

fn main() {
    println!("lungmotion: validation and benchmarks land with the simulation core");
}
