// Nearest target points of the batched windowed ICP (slipmap.core.opencl.nearest).
//
// Targets are sorted by the column of a 2D (x, y) grid of cell size h; colstart[c] ..
// colstart[c + 1] are the targets of column c = row * nx + col. A query searches rings of
// columns around its own (Chebyshev rings r = 0, 1, ...) and stops when no target of ring r
// can be nearer than the K-th best so far: a target in ring r >= 1 is at least
// (r - 1) h + e away, e the query's distance to the nearest edge of its own column.
//
// Each source point keeps the K = 4 nearest targets of its last search and where it was
// (the numpy _Matcher's cache, slipmap.core.icp_cells): moved by less than half the gap
// between the first and the second, the first is still its nearest; by less than half the
// gap between the first and the fourth, its nearest is one of the four (triangle
// inequality). Only the other points search the grid again.

#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#define KC 4  // nearest.py CANDIDATES
#define KMAX 64

static double dist2(__global const double *tp, int k, double x, double y, double z)
{
    double dx = tp[3 * k] - x, dy = tp[3 * k + 1] - y, dz = tp[3 * k + 2] - z;
    return dx * dx + dy * dy + dz * dz;
}

// the kk nearest targets of (x, y, z): sorted squared distances d[] (INFINITY: none) and
// sorted-target indices j[] (-1: none); ties go to the smaller sorted index
static void grid_knn(__global const double *tp, __global const int *colstart, long nx,
                     long ny, double x0, double y0, double h, double x, double y, double z,
                     int kk, double *d, int *j)
{
    for (int m = 0; m < kk; m++) {
        d[m] = INFINITY;
        j[m] = -1;
    }
    double fx = (x - x0) / h, fy = (y - y0) / h;
    double cxf = clamp(floor(fx), -1.0e9, 1.0e9), cyf = clamp(floor(fy), -1.0e9, 1.0e9);
    long cx = (long)cxf, cy = (long)cyf;
    double e = fmax(fmin(fmin(fx - cxf, cxf + 1.0 - fx), fmin(fy - cyf, cyf + 1.0 - fy)), 0.0) * h;
    long dxo = cx < 0 ? -cx : (cx >= nx ? cx - nx + 1 : 0);
    long dyo = cy < 0 ? -cy : (cy >= ny ? cy - ny + 1 : 0);
    long r0 = max(dxo, dyo);
    long rmax = r0 + max(nx, ny);
    for (long r = r0; r <= rmax; r++) {
        if (r > 0) {
            double lb = ((double)(r - 1) * h + e) * (1.0 - 1.0e-12);
            if (lb > 0.0 && lb * lb > d[kk - 1]) break;
        }
        long ylo = max(cy - r, (long)0), yhi = min(cy + r, ny - 1);
        for (long yy = ylo; yy <= yhi; yy++) {
            int edge = (yy == cy - r) || (yy == cy + r);
            long xlo = edge ? max(cx - r, (long)0) : cx - r;
            long xhi = edge ? min(cx + r, nx - 1) : cx + r;
            long step = (edge || r == 0) ? 1 : 2 * r;
            for (long xx = xlo; xx <= xhi; xx += step) {
                if (xx < 0 || xx >= nx) continue;
                long c = yy * nx + xx;
                int k1 = colstart[c + 1];
                for (int k = colstart[c]; k < k1; k++) {
                    double dk = dist2(tp, k, x, y, z);
                    if (dk < d[kk - 1] || (dk == d[kk - 1] && k < j[kk - 1])) {
                        int m = kk - 1;
                        while (m > 0 && (dk < d[m - 1] || (dk == d[m - 1] && k < j[m - 1]))) {
                            d[m] = d[m - 1];
                            j[m] = j[m - 1];
                            m--;
                        }
                        d[m] = dk;
                        j[m] = k;
                    }
                }
            }
        }
    }
}

// The nearest target (sorted index, -1: none) of the moved source point (x, y, z) of cell c
// with cache slot g: within the gate and the cell's box.
static int match_point(__global const double *tp, __global const int *colstart, long nx,
                       long ny, double x0, double y0, double h, __global const double *boxes,
                       int use_boxes, double gate2, int c, long g, double x, double y,
                       double z, __global double *last, __global double *margin1,
                       __global double *marginc, __global int *cand)
{
    double mx = x - last[3 * g], my = y - last[3 * g + 1], mz = z - last[3 * g + 2];
    double move2 = mx * mx + my * my + mz * mz;
    double m1 = margin1[g], mc = marginc[g];
    int j;
    if (m1 > 0.0 && move2 < m1 * m1) {
        j = cand[KC * g];
    } else if (mc > 0.0 && move2 < mc * mc) {
        j = -1;
        double best = INFINITY;
        for (int m = 0; m < KC; m++) {
            int k = cand[KC * g + m];
            if (k < 0) continue;
            double dk = dist2(tp, k, x, y, z);
            if (dk < best || (dk == best && k < j)) {
                best = dk;
                j = k;
            }
        }
    } else {
        double d[KC];
        int jj[KC];
        grid_knn(tp, colstart, nx, ny, x0, y0, h, x, y, z, KC, d, jj);
        last[3 * g] = x;
        last[3 * g + 1] = y;
        last[3 * g + 2] = z;
        for (int m = 0; m < KC; m++) cand[KC * g + m] = jj[m];
        double d0 = sqrt(d[0]);
        margin1[g] = isfinite(d[0]) ? 0.5 * (sqrt(d[1]) - d0) : -1.0;
        marginc[g] = isfinite(d[0]) ? 0.5 * (sqrt(d[KC - 1]) - d0) : -1.0;
        j = jj[0];
    }
    if (j >= 0 && !(dist2(tp, j, x, y, z) <= gate2)) j = -1;
    if (j >= 0 && use_boxes) {
        double tx = tp[3 * j], ty = tp[3 * j + 1];
        if (!(tx >= boxes[4 * c] && tx <= boxes[4 * c + 1] && ty >= boxes[4 * c + 2]
              && ty <= boxes[4 * c + 3]))
            j = -1;
    }
    return j;
}

// q = lin[c] s + t[c] of source point s (centred on its cell) of a rigid or affine cell
static void transform(__global const double *lin, __global const double *t, int c, double sx,
                      double sy, double sz, double *q)
{
    for (int r = 0; r < 3; r++)
        q[r] = lin[9 * c + 3 * r] * sx + lin[9 * c + 3 * r + 1] * sy + lin[9 * c + 3 * r + 2] * sz
               + t[3 * c + r];
}

// For each of n moved source points: q (centred on its cell), its cell seg, its index g
// into the per-point cache (last, margin1, marginc, cand). out[i]: the original index of
// its nearest target when within the gate and the cell's box, else -1.
__kernel void cell_nearest(__global const double *tp, __global const int *colstart,
                           __global const int *perm, const long nx, const long ny,
                           const double x0, const double y0, const double h,
                           __global const double *centres, __global const double *boxes,
                           const int use_boxes, const double gate2,
                           __global const double *q, __global const int *seg,
                           __global const int *gi, const long n,
                           __global double *last, __global double *margin1,
                           __global double *marginc, __global int *cand,
                           __global int *out)
{
    long i = get_global_id(0);
    if (i >= n) return;
    int c = seg[i];
    long g = gi[i];
    int j = match_point(tp, colstart, nx, ny, x0, y0, h, boxes, use_boxes, gate2, c, g,
                        q[3 * i] + centres[3 * c], q[3 * i + 1] + centres[3 * c + 1],
                        q[3 * i + 2] + centres[3 * c + 2], last, margin1, marginc, cand);
    out[i] = j >= 0 ? perm[j] : -1;
}

// One iteration's pairs of the source points pm[0 .. n-1] (indices into src, seg and the
// cache): each moved by its cell's transform (lin, t), then cell_nearest. out: original
// target index (-1: none); out_sorted: its index in tp.
__kernel void cell_match(__global const double *tp, __global const int *colstart,
                         __global const int *perm, const long nx, const long ny,
                         const double x0, const double y0, const double h,
                         __global const double *centres, __global const double *boxes,
                         const int use_boxes, const double gate2,
                         __global const double *src, __global const int *seg,
                         __global const int *pm, const long n, __global const double *lin,
                         __global const double *t, __global double *last,
                         __global double *margin1, __global double *marginc,
                         __global int *cand, __global int *out, __global int *out_sorted)
{
    long i = get_global_id(0);
    if (i >= n) return;
    long g = pm[i];
    int c = seg[g];
    double q[3];
    transform(lin, t, c, src[3 * g], src[3 * g + 1], src[3 * g + 2], q);
    int j = match_point(tp, colstart, nx, ny, x0, y0, h, boxes, use_boxes, gate2, c, g,
                        q[0] + centres[3 * c], q[1] + centres[3 * c + 1],
                        q[2] + centres[3 * c + 2], last, margin1, marginc, cand);
    out[i] = j >= 0 ? perm[j] : -1;
    out_sorted[i] = j;
}

// The rigid point-to-plane rows of the pairs of cell_match: ok[i] (a pair with a finite
// normal), the residual v = n . (q - m), the Jacobian row (q x n, n) and q . q, with m the
// target relative to the cell's centre and n its normal (normals: original order).
__kernel void cell_residuals(__global const double *tp, __global const double *centres,
                             __global const double *src, __global const int *seg,
                             __global const int *pm, const long n,
                             __global const double *lin, __global const double *t,
                             __global const double *normals, __global const int *out,
                             __global const int *out_sorted, __global int *ok,
                             __global double *v, __global double *A, __global double *qq)
{
    long i = get_global_id(0);
    if (i >= n) return;
    int j = out[i], js = out_sorted[i];
    ok[i] = 0;
    if (j < 0) return;
    double nx = normals[3 * (long)j], ny = normals[3 * (long)j + 1];
    double nz = normals[3 * (long)j + 2];
    if (!(isfinite(nx) && isfinite(ny) && isfinite(nz))) return;
    long g = pm[i];
    int c = seg[g];
    double q[3];
    transform(lin, t, c, src[3 * g], src[3 * g + 1], src[3 * g + 2], q);
    double dx = q[0] - (tp[3 * js] - centres[3 * c]);
    double dy = q[1] - (tp[3 * js + 1] - centres[3 * c + 1]);
    double dz = q[2] - (tp[3 * js + 2] - centres[3 * c + 2]);
    ok[i] = 1;
    v[i] = nx * dx + ny * dy + nz * dz;
    A[6 * i] = q[1] * nz - q[2] * ny;
    A[6 * i + 1] = q[2] * nx - q[0] * nz;
    A[6 * i + 2] = q[0] * ny - q[1] * nx;
    A[6 * i + 3] = nx;
    A[6 * i + 4] = ny;
    A[6 * i + 5] = nz;
    qq[i] = q[0] * q[0] + q[1] * q[1] + q[2] * q[2];
}

// Unit normals of targets ids[0 .. n-1] (original indices; iperm: original -> sorted) from
// their kk nearest targets (the point itself included): the smallest-eigenvalue eigenvector
// of the neighbourhood's covariance, oriented z >= 0, by the closed form of
// slipmap.core.icp._pca_normals (the characteristic cubic's trigonometric roots, the largest
// cross product of two rows of C - e0 I). hard[i] = 1 where the two smallest eigenvalues
// nearly coincide: the host recomputes those with eigh (as _pca_normals does).
__kernel void target_normals(__global const double *tp, __global const int *colstart,
                             const long nx, const long ny, const double x0, const double y0,
                             const double h, __global const int *iperm,
                             __global const long *ids, const long n, const int kk,
                             __global double *out, __global int *hard)
{
    long i = get_global_id(0);
    if (i >= n) return;
    int s = iperm[ids[i]];
    double d[KMAX];
    int jj[KMAX];
    grid_knn(tp, colstart, nx, ny, x0, y0, h, tp[3 * s], tp[3 * s + 1], tp[3 * s + 2], kk, d,
             jj);
    double mx = 0.0, my = 0.0, mz = 0.0;
    for (int m = 0; m < kk; m++) {
        mx += tp[3 * jj[m]];
        my += tp[3 * jj[m] + 1];
        mz += tp[3 * jj[m] + 2];
    }
    mx /= kk;
    my /= kk;
    mz /= kk;
    double a00 = 0.0, a11 = 0.0, a22 = 0.0, a01 = 0.0, a02 = 0.0, a12 = 0.0;
    for (int m = 0; m < kk; m++) {
        double ux = tp[3 * jj[m]] - mx, uy = tp[3 * jj[m] + 1] - my, uz = tp[3 * jj[m] + 2] - mz;
        a00 += ux * ux;
        a11 += uy * uy;
        a22 += uz * uz;
        a01 += ux * uy;
        a02 += ux * uz;
        a12 += uy * uz;
    }
    double q = (a00 + a11 + a22) / 3.0;
    double b00 = a00 - q, b11 = a11 - q, b22 = a22 - q;
    double p = sqrt((b00 * b00 + b11 * b11 + b22 * b22
                     + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0);
    double det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
                 + a02 * (a01 * a12 - b11 * a02);
    double pp = p > 0.0 ? p : 1.0;
    double r = clamp(det / (2.0 * pp * pp * pp), -1.0, 1.0);
    double phi = acos(r) / 3.0;
    double e2 = q + 2.0 * p * cos(phi);
    double e0 = q + 2.0 * p * cos(phi + 2.0 * M_PI / 3.0);
    double e1 = 3.0 * q - e2 - e0;
    double r0[3] = {a00 - e0, a01, a02}, r1[3] = {a01, a11 - e0, a12}, r2[3] = {a02, a12, a22 - e0};
    double c[3][3];
    c[0][0] = r0[1] * r1[2] - r0[2] * r1[1];
    c[0][1] = r0[2] * r1[0] - r0[0] * r1[2];
    c[0][2] = r0[0] * r1[1] - r0[1] * r1[0];
    c[1][0] = r0[1] * r2[2] - r0[2] * r2[1];
    c[1][1] = r0[2] * r2[0] - r0[0] * r2[2];
    c[1][2] = r0[0] * r2[1] - r0[1] * r2[0];
    c[2][0] = r1[1] * r2[2] - r1[2] * r2[1];
    c[2][1] = r1[2] * r2[0] - r1[0] * r2[2];
    c[2][2] = r1[0] * r2[1] - r1[1] * r2[0];
    int best = 0;
    double nn = -1.0;
    for (int m = 0; m < 3; m++) {
        double v = c[m][0] * c[m][0] + c[m][1] * c[m][1] + c[m][2] * c[m][2];
        if (v > nn) {
            nn = v;
            best = m;
        }
    }
    double norm = sqrt(fmax(nn, 1e-300));
    double sgn = c[best][2] < 0.0 ? -1.0 : 1.0;
    out[3 * i] = sgn * c[best][0] / norm;
    out[3 * i + 1] = sgn * c[best][1] / norm;
    out[3 * i + 2] = sgn * c[best][2] / norm;
    double scale = fmax(e2, 1e-300);
    hard[i] = !((e1 - e0 > 1e-3 * scale) && (e1 > 1e-6 * scale));
}
