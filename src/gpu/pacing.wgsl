// The cover-paced table (TrainConfig::cover_paced_table) on the device: the CPU trainer's
// Pacing per parameter. `open_gate` runs after the cover's backward pass, `hold_back` after
// every scene's and before Adam. Only table parameters (index ≥ n_matrix) are visited.

struct PacingParams {
    // Table parameters, and the first one's index in the gradient.
    n_table: u32,
    n_matrix: u32,
    // Invocations per dispatch row (dispatches wider than 65535 workgroups fold into y).
    row_width: u32,
    _pad: u32,
}

@group(0) @binding(0) var<storage, read_write> grad: array<f32>;
@group(0) @binding(1) var<storage, read_write> gate: array<u32>;
@group(0) @binding(2) var<storage, read_write> pending: array<f32>;
@group(0) @binding(3) var<uniform> p: PacingParams;

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
    } else {
        pending[j] = pending[j] + grad[i];
        grad[i] = 0.0;
    }
    gate[j] = 0u;
}
