//! Physics steps/s of the standing Aliengo under PD through our safe layer
//! (`Robot::pd_substep`: checked `Data::step`, slices, warnings check) versus the
//! same PD law and bare `mj_step` on the raw FFI, same model, same run.
//! Target ratio >= 0.97. `cargo bench --bench physics`; the summary line
//! prints both rates and their ratio from an interleaved side-by-side run.

/// The allocator the `rall` binary runs with (large buffers on huge pages).
#[global_allocator]
static ALLOCATOR: rall::memory::HugePageAlloc = rall::memory::HugePageAlloc;

use std::hint::black_box;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use rall::robot::{ControlConfig, Robot, NUM_JOINTS};
use rall::sim::raw_bench::{raw_pd_steps, RawPd};
use rall::sim::{Data, Model};

const FLAT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/flat.xml");
const STEPS: usize = 1000;

fn settled_robot() -> Robot {
    let mut robot = Robot::load(FLAT, ControlConfig::default()).unwrap();
    let target = robot.default_q_rad;
    for _ in 0..400 {
        robot.pd_substep(&target).unwrap();
    }
    robot
}

fn ours(robot: &mut Robot, n: usize) {
    let target = robot.default_q_rad;
    for _ in 0..n {
        black_box(robot.pd_substep(&target).unwrap());
    }
}

/// A settled robot's model copy and state, stepped on the raw FFI.
struct RawRobot {
    robot: Robot,
    model: Model,
    data: Data,
}

fn raw_robot() -> RawRobot {
    let robot = settled_robot();
    let model = robot.model_copy().unwrap();
    let mut data = Data::new(&model).unwrap();
    data.qpos_mut().copy_from_slice(robot.data().qpos());
    data.qvel_mut().copy_from_slice(robot.data().qvel());
    data.forward(&model).unwrap();
    RawRobot { robot, model, data }
}

fn raw(r: &mut RawRobot, n: usize) {
    let robot = &r.robot;
    let limits: [f64; NUM_JOINTS] = std::array::from_fn(|i| robot.control.torque_limit_nm(i));
    let pd = RawPd {
        qpos_adr: &robot.layout.qpos_adr,
        dof_adr: &robot.layout.dof_adr,
        actuator: &robot.layout.actuator_ids,
        target_rad: &robot.default_q_rad,
        kp: robot.control.kp_nm_per_rad,
        kd: robot.control.kd_nm_s_per_rad,
        limit_nm: &limits,
    };
    raw_pd_steps(&r.model, &mut r.data, n, &pd).unwrap();
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("physics_standing_aliengo_pd");
    g.throughput(Throughput::Elements(STEPS as u64));
    let mut r = raw_robot();
    g.bench_function("raw_ffi_mj_step", |b| b.iter(|| raw(&mut r, STEPS)));
    let mut robot = settled_robot();
    g.bench_function("safe_layer_step", |b| b.iter(|| ours(&mut robot, STEPS)));
    g.finish();
    print_side_by_side();
}

/// Interleaved rounds so both loops see the same machine load.
fn print_side_by_side() {
    let rounds = 30;
    let (mut t_raw, mut t_ours) = (0.0, 0.0);
    let (mut a, mut b) = (raw_robot(), settled_robot());
    for _ in 0..rounds {
        let t = Instant::now();
        raw(&mut a, STEPS);
        t_raw += t.elapsed().as_secs_f64();
        let t = Instant::now();
        ours(&mut b, STEPS);
        t_ours += t.elapsed().as_secs_f64();
    }
    let n = (rounds * STEPS) as f64;
    println!(
        "physics summary: raw FFI {:.0} steps/s | safe layer {:.0} steps/s | ratio safe/raw {:.3} (target >= 0.97)",
        n / t_raw,
        n / t_ours,
        t_raw / t_ours
    );
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(3));
    targets = bench
}
criterion_main!(benches);
