// The 8 corner indices of one cell per (item, level): what the hash-grid forward computes
// before it gathers features. Item i's cell on level l is cells[3·(i·L + l) ..][0..3]; its
// corners go to corners_out[8·(i·L + l) ..][0..8]. Concatenated after index.wgsl.

struct CornerParams {
    n_items: u32,
    n_levels: u32,
    // Invocations per dispatch row (dispatches wider than 65535 workgroups fold into y).
    row_width: u32,
    _pad: u32,
}

@group(0) @binding(0) var<storage, read> index_levels: array<LevelIndex>;
@group(0) @binding(1) var<storage, read> index_tables: array<u32>;
@group(0) @binding(2) var<storage, read> cells: array<u32>;
@group(0) @binding(3) var<storage, read_write> corners_out: array<u32>;
@group(0) @binding(4) var<uniform> params: CornerParams;

// One level per workgroup (gid.z): the level's kind is uniform across it, so a GPU runs only
// that kind's branch of the index functions.
@compute @workgroup_size(64)
fn corners_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let item = gid.x + gid.y * params.row_width;
    if (item >= params.n_items) {
        return;
    }
    let pair = item * params.n_levels + gid.z;
    let lv = index_levels[gid.z];
    let cell = vec3<u32>(cells[3u * pair], cells[3u * pair + 1u], cells[3u * pair + 2u]);
    let out = level_corners(lv, cell);
    for (var c = 0u; c < 8u; c++) {
        corners_out[8u * pair + c] = out[c];
    }
}
