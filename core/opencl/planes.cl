/* SlipMap OpenCL kernels: Morton encoding, per-node plane moments and planarity count,
 * connected-component labelling (Kusari et al. 2019, sections II.A-C).
 *
 * Double precision throughout. Floating-point contraction (fma) is switched off so that
 * every product and sum is rounded as numpy rounds it: the Morton keys are bit-identical to
 * core.octree.quantise_encode, and node centroids and covariances are bit-identical to
 * NumpyKernels.node_fit (numpy's pairwise summation order is reproduced below). Point-to-plane
 * distances are summed in a fixed order; numpy's einsum order depends on its SIMD path, so a
 * distance may differ by an ulp.
 *
 * Index arguments are 64-bit (long) except in the labelling kernels, whose labels are 32-bit
 * ints so that OpenCL 1.1 atomic_min works on them (the host checks n < 2**31).
 */

#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

/* Bit i of the low 21 bits of v moves to bit 3*i (core.octree._spread_bits). */
inline ulong spread_bits(ulong v)
{
    ulong x = v & 0x1FFFFFUL;
    x = (x | (x << 32)) & 0x1F00000000FFFFUL;
    x = (x | (x << 16)) & 0x1F0000FF0000FFUL;
    x = (x | (x << 8)) & 0x100F00F00F00F00FUL;
    x = (x | (x << 4)) & 0x10C30C30C30C30C3UL;
    x = (x | (x << 2)) & 0x1249249249249249UL;
    return x;
}

/* floor((p - lo) * scale) clipped to [0, top], as core.octree.quantise_encode. A NaN
 * coordinate gives cell 0 (numpy: NaN -> int64 min -> low 21 bits 0, the same key bits). */
inline ulong cell_of(double p, double lo, double scale, double top)
{
    double c = floor((p - lo) * scale);
    c = fmin(fmax(c, 0.0), top);
    return (ulong)c;
}

/* One work-item per point: Morton key, x in bit 0, y in bit 1, z in bit 2. */
__kernel void morton_encode(__global const double *pts, const double lox, const double loy,
                            const double loz, const double scale, const double top,
                            __global ulong *keys, const long n)
{
    const long i = get_global_id(0);
    if (i >= n)
        return;
    const ulong cx = cell_of(pts[3 * i], lox, scale, top);
    const ulong cy = cell_of(pts[3 * i + 1], loy, scale, top);
    const ulong cz = cell_of(pts[3 * i + 2], loz, scale, top);
    keys[i] = spread_bits(cx) | (spread_bits(cy) << 1) | (spread_bits(cz) << 2);
}

/* ---- numpy's pairwise summation, reproduced so that node moments are bit-identical ----
 *
 * np.add.reduceat over a segment returns first + pairwise(rest), where pairwise (numpy
 * loops_utils.h, unchanged since numpy 1.9) sums fewer than 8 values in order from -0.0,
 * up to 128 values with 8 interleaved accumulators combined as ((0+1)+(2+3))+((4+5)+(6+7))
 * then the remainder in order, and longer runs as pairwise(left) + pairwise(right) with the
 * left length n/2 rounded down to a multiple of 8. The eight lanes of a double8 carry the
 * sums of several columns at once (element-wise, so each lane rounds exactly as numpy). */

#define PW_BLOCK 128
#define PW_DEPTH 48 /* stack levels: enough for 2**50 points in one node */

/* The values summed: mode 0 the coordinates, mode 1 the centred products
 * xx, yy, zz, xy, xz, yz (centred on mx, my, mz). */
inline double8 pw_value(__global const double *pts, long i, int mode, double mx, double my,
                        double mz)
{
    const double x = pts[3 * i], y = pts[3 * i + 1], z = pts[3 * i + 2];
    if (mode == 0)
        return (double8)(x, y, z, 0.0, 0.0, 0.0, 0.0, 0.0);
    const double dx = x - mx, dy = y - my, dz = z - mz;
    return (double8)(dx * dx, dy * dy, dz * dz, dx * dy, dx * dz, dy * dz, 0.0, 0.0);
}

inline double8 pw_leaf(__global const double *pts, long off, long len, int mode, double mx,
                       double my, double mz)
{
    if (len < 8) {
        double8 res = (double8)(-0.0);
        for (long i = 0; i < len; ++i)
            res += pw_value(pts, off + i, mode, mx, my, mz);
        return res;
    }
    double8 r0 = pw_value(pts, off, mode, mx, my, mz);
    double8 r1 = pw_value(pts, off + 1, mode, mx, my, mz);
    double8 r2 = pw_value(pts, off + 2, mode, mx, my, mz);
    double8 r3 = pw_value(pts, off + 3, mode, mx, my, mz);
    double8 r4 = pw_value(pts, off + 4, mode, mx, my, mz);
    double8 r5 = pw_value(pts, off + 5, mode, mx, my, mz);
    double8 r6 = pw_value(pts, off + 6, mode, mx, my, mz);
    double8 r7 = pw_value(pts, off + 7, mode, mx, my, mz);
    const long lim = len - (len % 8);
    long i = 8;
    for (; i < lim; i += 8) {
        r0 += pw_value(pts, off + i, mode, mx, my, mz);
        r1 += pw_value(pts, off + i + 1, mode, mx, my, mz);
        r2 += pw_value(pts, off + i + 2, mode, mx, my, mz);
        r3 += pw_value(pts, off + i + 3, mode, mx, my, mz);
        r4 += pw_value(pts, off + i + 4, mode, mx, my, mz);
        r5 += pw_value(pts, off + i + 5, mode, mx, my, mz);
        r6 += pw_value(pts, off + i + 6, mode, mx, my, mz);
        r7 += pw_value(pts, off + i + 7, mode, mx, my, mz);
    }
    double8 res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7));
    for (; i < len; ++i)
        res += pw_value(pts, off + i, mode, mx, my, mz);
    return res;
}

inline long pw_half(long n)
{
    const long h = n / 2;
    return h - h % 8;
}

/* pairwise(values off .. off + len - 1): the recursion unrolled on an explicit stack. */
inline double8 pw_sum(__global const double *pts, long off, long len, int mode, double mx,
                      double my, double mz)
{
    if (len <= PW_BLOCK)
        return pw_leaf(pts, off, len, mode, mx, my, mz);
    long s_off[PW_DEPTH], s_len[PW_DEPTH];
    int s_state[PW_DEPTH]; /* 1: left child pending, 2: right child pending */
    double8 s_left[PW_DEPTH];
    int sp = 0;
    s_off[0] = off;
    s_len[0] = len;
    for (;;) {
        const long o = s_off[sp], l = s_len[sp];
        if (l > PW_BLOCK && sp + 1 < PW_DEPTH) {
            s_state[sp] = 1;
            ++sp;
            s_off[sp] = o;
            s_len[sp] = pw_half(l);
            continue;
        }
        double8 ret = pw_leaf(pts, o, l, mode, mx, my, mz);
        for (;;) { /* pop finished frames */
            if (sp == 0)
                return ret;
            --sp;
            if (s_state[sp] == 1) {
                const long h = pw_half(s_len[sp]);
                s_left[sp] = ret;
                s_state[sp] = 2;
                ++sp;
                s_off[sp] = s_off[sp - 1] + h;
                s_len[sp] = s_len[sp - 1] - h;
                break;
            }
            ret = s_left[sp] + ret;
        }
    }
}

/* np.add.reduceat over one segment: first value + pairwise(the others). */
inline double8 segment_sum(__global const double *pts, long s, long c, int mode, double mx,
                           double my, double mz)
{
    return pw_value(pts, s, mode, mx, my, mz) + pw_sum(pts, s + 1, c - 1, mode, mx, my, mz);
}

/* One work-item per node: centroid, and covariance = centred scatter / count (two passes,
 * as NumpyKernels.node_fit). cov holds xx, yy, zz, xy, xz, yz per node. */
__kernel void node_moments(__global const double *pts, __global const long *starts,
                           __global const long *counts, const long m, __global double *mean,
                           __global double *cov)
{
    const long k = get_global_id(0);
    if (k >= m)
        return;
    const long s = starts[k];
    const long c = counts[k];
    if (c <= 0) {
        for (int j = 0; j < 3; ++j)
            mean[3 * k + j] = NAN;
        for (int j = 0; j < 6; ++j)
            cov[6 * k + j] = NAN;
        return;
    }
    const double cd = (double)c;
    const double8 sm = segment_sum(pts, s, c, 0, 0.0, 0.0, 0.0);
    const double mx = sm.s0 / cd, my = sm.s1 / cd, mz = sm.s2 / cd;
    const double8 sc = segment_sum(pts, s, c, 1, mx, my, mz);
    mean[3 * k] = mx;
    mean[3 * k + 1] = my;
    mean[3 * k + 2] = mz;
    cov[6 * k] = sc.s0 / cd;
    cov[6 * k + 1] = sc.s1 / cd;
    cov[6 * k + 2] = sc.s2 / cd;
    cov[6 * k + 3] = sc.s3 / cd;
    cov[6 * k + 4] = sc.s4 / cd;
    cov[6 * k + 5] = sc.s5 / cd;
}

/* One work-item per node: signed distance of each of its points to the node's plane
 * (centroid mean, unit normal), the within flag |d| <= threshold and the node's count. */
__kernel void node_within(__global const double *pts, __global const long *starts,
                          __global const long *counts, const long m,
                          __global const double *mean, __global const double *normal,
                          const double threshold, __global uchar *within,
                          __global long *n_within)
{
    const long k = get_global_id(0);
    if (k >= m)
        return;
    const long s = starts[k];
    const long e = s + counts[k];
    const double mx = mean[3 * k], my = mean[3 * k + 1], mz = mean[3 * k + 2];
    const double nx = normal[3 * k], ny = normal[3 * k + 1], nz = normal[3 * k + 2];
    long cnt = 0;
    for (long i = s; i < e; ++i) {
        const double d = (pts[3 * i] - mx) * nx + (pts[3 * i + 1] - my) * ny
                         + (pts[3 * i + 2] - mz) * nz;
        const int w = fabs(d) <= threshold;
        within[i] = (uchar)w;
        cnt += w;
    }
    n_within[k] = cnt;
}

/* Min-label propagation (Algorithm 2), one work-item per node that has edges (CSR row k is
 * node nodes[k]). Labels only decrease, and a node's label is always a node of its component
 * that is <= the node itself, so concurrent updates are safe. Besides its own label, a node
 * lowers the label of its current label (hooking), which shortens the chains that pointer
 * jumping then collapses. */
__kernel void cc_hook(__global const long *indptr, __global const int *indices,
                      __global const int *nodes, const int n_rows, volatile __global int *lab,
                      __global int *changed)
{
    const int k = get_global_id(0);
    if (k >= n_rows)
        return;
    const int u = nodes[k];
    const int lu = lab[u];
    int m = lu;
    const long e = indptr[k + 1];
    for (long j = indptr[k]; j < e; ++j)
        m = min(m, lab[indices[j]]);
    if (m < lu) {
        atomic_min(&lab[u], m);
        atomic_min(&lab[lu], m);
        *changed = 1;
    }
}

/* Pointer jumping: follow labels until a node labelled with itself. */
__kernel void cc_jump(__global const int *nodes, const int n_rows, volatile __global int *lab)
{
    const int k = get_global_id(0);
    if (k >= n_rows)
        return;
    const int u = nodes[k];
    int l = lab[u];
    int ll = lab[l];
    while (ll != l) {
        l = ll;
        ll = lab[l];
    }
    lab[u] = l;
}
