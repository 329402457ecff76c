// The gate with hold-back of the training hooks (ngp::train::hooks) on the device: the CPU
// trainer's HoldBack per parameter. A policy runs `open_gate` and `hold_back` when it asks
// (stealth: after the cover's backward pass, and before Adam). Only table parameters
// (index ≥ n_matrix) are visited. `bound` holds, per table entry, its magnitude bound,
// negative for none: a bounded entry's gate is open, and `clamp_bounded` holds it within its
// bound after Adam.

struct HeldParams {
    // Table parameters, and the first one's index in the gradient.
    n_table: u32,
    n_matrix: u32,
    // Invocations per dispatch row (dispatches wider than 65535 workgroups fold into y).
    row_width: u32,
    n_features: u32,
}

@group(0) @binding(0) var<storage, read_write> grad: array<f32>;
@group(0) @binding(1) var<storage, read_write> gate: array<u32>;
@group(0) @binding(2) var<storage, read_write> pending: array<f32>;
@group(0) @binding(3) var<uniform> p: HeldParams;
@group(0) @binding(4) var<storage, read> bound: array<f32>;
@group(0) @binding(5) var<storage, read_write> weights: array<f32>;

// The gradient so far reaches the parameter this step.
@compute @workgroup_size(256)
fn open_gate(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x + gid.y * p.row_width;
    if (j >= p.n_table) {
        return;
    }
    gate[j] = select(0u, 1u, grad[p.n_matrix + j] != 0.0);
}

// Gradients of parameters whose gate is closed wait in `pending` (bounded entries excepted);
// those whose gate is open take what waited. The gate closes for the next step.
@compute @workgroup_size(256)
fn hold_back(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x + gid.y * p.row_width;
    if (j >= p.n_table) {
        return;
    }
    let i = p.n_matrix + j;
    if (gate[j] != 0u) {
        grad[i] = grad[i] + pending[j];
        pending[j] = 0.0;
    } else if (bound[j / p.n_features] < 0.0) {
        pending[j] = pending[j] + grad[i];
        grad[i] = 0.0;
    }
    gate[j] = 0u;
}

// After Adam: every bounded entry within its bound.
@compute @workgroup_size(256)
fn clamp_bounded(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x + gid.y * p.row_width;
    if (j >= p.n_table) {
        return;
    }
    let b = bound[j / p.n_features];
    if (b >= 0.0) {
        let i = p.n_matrix + j;
        weights[i] = clamp(weights[i], -b, b);
    }
}
