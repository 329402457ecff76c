// The cover-paced table (TrainConfig::cover_paced_table) on the device: the CPU trainer's
// Pacing per parameter. `open_gate` runs after the cover's backward pass, `hold_back` after
// every scene's and before Adam. Only table parameters (index ≥ n_matrix) are visited.
// `bound` holds, per table entry, the magnitude bound of an entry the cover has left
// (TrainConfig::bounded_left_entries), negative for one it reaches: a left entry's gate is
// open, and `clamp_left` holds it within its bound after Adam.

struct PacingParams {
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
@group(0) @binding(3) var<uniform> p: PacingParams;
@group(0) @binding(4) var<storage, read> bound: array<f32>;
@group(0) @binding(5) var<storage, read_write> weights: array<f32>;

// The cover's gradient reached the parameter this step.
@compute @workgroup_size(256)
fn open_gate(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x + gid.y * p.row_width;
    if (j >= p.n_table) {
        return;
    }
    gate[j] = select(0u, 1u, grad[p.n_matrix + j] != 0.0);
}

// Gradients of parameters the cover did not reach wait in `pending`; those it reached take
// what waited. The gate closes for the next step.
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

// After Adam: every left entry within its bound.
@compute @workgroup_size(256)
fn clamp_left(@builtin(global_invocation_id) gid: vec3<u32>) {
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
