// Adam + EMA over the whole parameter vector, one invocation per parameter: the CPU
// optimizer's update (ngp::train::optimizer) without its touched-group bookkeeping, which
// only lets the CPU skip memory it would otherwise stream; here every parameter is visited,
// and the rule that decides whether Adam runs is the same: always for MLP ("matrix")
// weights, for grid entries only when their gradient is non-zero. The EMA is brought up to
// date for every parameter every step, which equals the CPU's lazy closed-form catch-up.

struct AdamParams {
    n: u32,
    n_matrix: u32,
    // Invocations per dispatch row (dispatches wider than 65535 workgroups fold into y).
    row_width: u32,
    _pad0: u32,
    lr: f32,
    beta1: f32,
    beta2: f32,
    epsilon: f32,
    l2_reg: f32,
    ema_decay: f32,
    _pad1: f32,
    _pad2: f32,
}

@group(0) @binding(0) var<storage, read_write> weights: array<f32>;
@group(0) @binding(1) var<storage, read_write> grad: array<f32>;
@group(0) @binding(2) var<storage, read_write> adam_m: array<f32>;
@group(0) @binding(3) var<storage, read_write> adam_v: array<f32>;
@group(0) @binding(4) var<storage, read_write> adam_steps: array<u32>;
@group(0) @binding(5) var<storage, read_write> ema: array<f32>;
// correction[t] = sqrt(1 − β2^t) / (1 − β1^t), computed on the host in f64 as the CPU does.
@group(0) @binding(6) var<storage, read> correction: array<f32>;
@group(0) @binding(7) var<uniform> p: AdamParams;

@compute @workgroup_size(256)
fn adam_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * p.row_width;
    if (i >= p.n) {
        return;
    }
    var g = grad[i];
    grad[i] = 0.0;
    var w = weights[i];
    let is_matrix = i < p.n_matrix;
    if (is_matrix || g != 0.0) {
        if (is_matrix) {
            g += p.l2_reg * w;
        }
        let t = adam_steps[i] + 1u;
        adam_steps[i] = t;
        let m = p.beta1 * adam_m[i] + (1.0 - p.beta1) * g;
        let v = p.beta2 * adam_v[i] + (1.0 - p.beta2) * g * g;
        adam_m[i] = m;
        adam_v[i] = v;
        w -= p.lr * correction[t] * m / (sqrt(v) + p.epsilon);
        weights[i] = w;
    }
    ema[i] = p.ema_decay * ema[i] + (1.0 - p.ema_decay) * w;
}
