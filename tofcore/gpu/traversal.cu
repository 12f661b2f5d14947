// Closest-hit and any-hit traversal of tofcore's 4-wide BVH records, one thread per ray.
//
// The twin of tofcore.scene.bvh.BVH.intersect / BVH.occluded (NumPy, breadth first); the records are read
// exactly as BVH.build lays them out (int32 words, floats stored as their bits):
//   node record at row r (WIDTH = 4 children per row):
//     rows r+0..r+2  child box minimum x, y, z      rows r+3..r+5  child box maximum x, y, z
//     row  r+6       child: >= 0 first row of the child's node record, < 0: ~(first row of a leaf record)
//     empty slots hold inverted infinite boxes (min = +inf, max = -inf) that no ray enters, because
//     the entry plane is chosen by the sign of the direction, as in NumPy.
//   leaf record at row l (leaf_size triangles per row):
//     rows l+0..l+8  v0 xyz, v1 xyz, v2 xyz          row l+9  triangle index (-1: padding, at the end)
//
// Every floating-point operation is written in the order of the NumPy code (bvh._ray_frame,
// bvh._watertight, BVH._trace) and compiled without FMA contraction (--fmad=false), so a ray gets the
// same t, u, v bit for bit; only a tie between two triangles at exactly the same t may be resolved
// differently (the traversal orders differ).

// The record layout (WIDTH, NODE_ROWS, LEAF_ROWS, CHILD_ROW, PRIM_ROW) and TINY_DIR are #defined from
// tofcore/scene/bvh.py's constants by traversal.py, which puts them in front of this source.
#define STACK_SIZE 96

struct Ray {
    float o[3];
    float d[3];
    float inv[3];
    float b1[3];
    float b2[3];
};

__device__ __forceinline__ void ray_frame(Ray& r) {
    // Duff et al. 2017, as bvh._ray_frame (float32).
    const float x = r.d[0], y = r.d[1], z = r.d[2];
    const float sign = z >= 0.0f ? 1.0f : -1.0f;
    const float a = -1.0f / (sign + z);
    const float b = x * y * a;
    r.b1[0] = 1.0f + sign * x * x * a;
    r.b1[1] = sign * b;
    r.b1[2] = -sign * x;
    r.b2[0] = b;
    r.b2[1] = sign + y * y * a;
    r.b2[2] = -y;
}

__device__ __forceinline__ float leaf_word(const int* leaves, int leaf_size, int row, int k) {
    return __int_as_float(leaves[row * leaf_size + k]);
}

// Watertight test (bvh._watertight); returns true with t, u, v on a hit with 0 < t < t_max.
__device__ __forceinline__ bool watertight(const Ray& r, const int* leaves, int leaf_size, int row, int k,
                                           float t_max, float& t_out, float& u_out, float& v_out) {
    float f[3][3];  // frame coordinates of the three vertices: (b1, b2, d)
    #pragma unroll
    for (int vtx = 0; vtx < 3; ++vtx) {
        const float rx = leaf_word(leaves, leaf_size, row + 3 * vtx + 0, k) - r.o[0];
        const float ry = leaf_word(leaves, leaf_size, row + 3 * vtx + 1, k) - r.o[1];
        const float rz = leaf_word(leaves, leaf_size, row + 3 * vtx + 2, k) - r.o[2];
        f[vtx][0] = rx * r.b1[0] + ry * r.b1[1] + rz * r.b1[2];
        f[vtx][1] = rx * r.b2[0] + ry * r.b2[1] + rz * r.b2[2];
        f[vtx][2] = rx * r.d[0] + ry * r.d[1] + rz * r.d[2];
    }
    const float a1 = f[0][0], a2 = f[0][1], a3 = f[0][2];
    const float p1 = f[1][0], p2 = f[1][1], p3 = f[1][2];
    const float c1 = f[2][0], c2 = f[2][1], c3 = f[2][2];
    const float w_u = c1 * p2 - c2 * p1;
    const float w_v = a1 * c2 - a2 * c1;
    const float w_w = p1 * a2 - p2 * a1;
    const bool same_sign = (w_u >= 0.0f && w_v >= 0.0f && w_w >= 0.0f) || (w_u <= 0.0f && w_v <= 0.0f && w_w <= 0.0f);
    if (!same_sign) return false;
    const float det = w_u + w_v + w_w;
    const float t = (w_u * a3 + w_v * p3 + w_w * c3) / det;
    if (!(t > 0.0f) || !(t < t_max)) return false;  // NaN (det = 0) never hits, as in NumPy
    t_out = t;
    u_out = w_v / det;
    v_out = w_w / det;
    return true;
}

template <bool ANY_HIT>
__device__ void traverse(const int* __restrict__ nodes, const int* __restrict__ leaves, int leaf_size,
                         const float* __restrict__ origins, const float* __restrict__ directions,
                         const float* __restrict__ t_max, const int* __restrict__ ignore_prim, long long n,
                         float* __restrict__ out_t, int* __restrict__ out_prim, float* __restrict__ out_u,
                         float* __restrict__ out_v, bool* __restrict__ out_occluded, int* status) {
    const long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    Ray r;
    #pragma unroll
    for (int a = 0; a < 3; ++a) {
        r.o[a] = origins[3 * i + a];
        const float d = directions[3 * i + a];
        r.d[a] = d;
        // bvh: 1.0 / safe_d in float64, rounded to float32
        const double safe = fabs((double)d) < TINY_DIR ? (d < 0.0f ? -TINY_DIR : TINY_DIR) : (double)d;
        r.inv[a] = (float)(1.0 / safe);
    }
    ray_frame(r);
    const int ignore = ignore_prim[i];
    float best = t_max[i];
    int best_prim = -1;
    float best_u = 0.0f, best_v = 0.0f;
    // entry/exit plane row offsets per axis: a negative direction enters at the box maximum
    int near_row[3], far_row[3];
    #pragma unroll
    for (int a = 0; a < 3; ++a) {
        const bool neg = r.d[a] < 0.0f;
        near_row[a] = neg ? 3 + a : a;
        far_row[a] = neg ? a : 3 + a;
    }

    int stack_node[STACK_SIZE];
    float stack_t[STACK_SIZE];
    int sp = 0;
    stack_node[sp] = 0;
    stack_t[sp] = 0.0f;
    ++sp;
    while (sp > 0) {
        --sp;
        const int node = stack_node[sp];
        if (stack_t[sp] > best) continue;  // entered before a nearer hit was found
        const int4* rec = reinterpret_cast<const int4*>(nodes) + node;  // row `node`, 4 children per row
        float t_in[WIDTH], t_out[WIDTH];
        #pragma unroll
        for (int a = 0; a < 3; ++a) {
            const int4 np = rec[near_row[a]];
            const int4 fp = rec[far_row[a]];
            const float nr[WIDTH] = {__int_as_float(np.x), __int_as_float(np.y), __int_as_float(np.z), __int_as_float(np.w)};
            const float fr[WIDTH] = {__int_as_float(fp.x), __int_as_float(fp.y), __int_as_float(fp.z), __int_as_float(fp.w)};
            #pragma unroll
            for (int c = 0; c < WIDTH; ++c) {
                const float near_t = (nr[c] - r.o[a]) * r.inv[a];
                const float far_t = (fr[c] - r.o[a]) * r.inv[a];
                if (a == 0) {
                    t_in[c] = near_t;
                    t_out[c] = far_t;
                } else {
                    t_in[c] = fmaxf(t_in[c], near_t);
                    t_out[c] = fminf(t_out[c], far_t);
                }
            }
        }
        const int4 ch = rec[CHILD_ROW];
        const int child[WIDTH] = {ch.x, ch.y, ch.z, ch.w};
        // inner children entered, to push far-to-near afterwards
        int push_node[WIDTH];
        float push_t[WIDTH];
        int n_push = 0;
        #pragma unroll
        for (int c = 0; c < WIDTH; ++c) {
            const float tin = fmaxf(t_in[c], 0.0f);
            const float tout = fminf(t_out[c], best);
            if (!(tin <= tout)) continue;
            if (child[c] >= 0) {
                push_node[n_push] = child[c];
                push_t[n_push] = tin;
                ++n_push;
                continue;
            }
            const int leaf = ~child[c];
            for (int k = 0; k < leaf_size; ++k) {
                const int prim = leaves[(leaf + PRIM_ROW) * leaf_size + k];
                if (prim < 0) break;  // padding
                if (prim == ignore) continue;
                float t, u, v;
                if (watertight(r, leaves, leaf_size, leaf, k, best, t, u, v)) {
                    if (ANY_HIT) {
                        out_occluded[i] = true;
                        return;
                    }
                    best = t;
                    best_prim = prim;
                    best_u = u;
                    best_v = v;
                }
            }
        }
        // sort the few entries by t, descending, so the nearest is popped first
        for (int a = 1; a < n_push; ++a) {
            const int nn = push_node[a];
            const float tt = push_t[a];
            int b = a - 1;
            while (b >= 0 && push_t[b] < tt) {
                push_node[b + 1] = push_node[b];
                push_t[b + 1] = push_t[b];
                --b;
            }
            push_node[b + 1] = nn;
            push_t[b + 1] = tt;
        }
        for (int a = 0; a < n_push; ++a) {
            if (sp < STACK_SIZE) {
                stack_node[sp] = push_node[a];
                stack_t[sp] = push_t[a];
                ++sp;
            } else {  // cannot happen for trees of depth <= STACK_SIZE / 3; reported, never silent
                atomicExch(status, 1);
                return;
            }
        }
    }
    if (ANY_HIT) {
        out_occluded[i] = false;
    } else {
        out_t[i] = best_prim >= 0 ? best : __int_as_float(0x7f800000);
        out_prim[i] = best_prim;
        out_u[i] = best_u;
        out_v[i] = best_v;
    }
}

extern "C" __global__ void closest_hit(const int* nodes, const int* leaves, int leaf_size, const float* origins,
                                       const float* directions, const float* t_max, const int* ignore_prim,
                                       long long n, float* out_t, int* out_prim, float* out_u, float* out_v,
                                       int* status) {
    traverse<false>(nodes, leaves, leaf_size, origins, directions, t_max, ignore_prim, n, out_t, out_prim, out_u,
                    out_v, nullptr, status);
}

extern "C" __global__ void any_hit(const int* nodes, const int* leaves, int leaf_size, const float* origins,
                                   const float* directions, const float* t_max, const int* ignore_prim,
                                   long long n, bool* out_occluded, int* status) {
    traverse<true>(nodes, leaves, leaf_size, origins, directions, t_max, ignore_prim, n, nullptr, nullptr, nullptr,
                   nullptr, out_occluded, status);
}
