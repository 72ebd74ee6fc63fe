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

#define KC 4

static double dist2(__global const double *tp, int k, double x, double y, double z)
{
    double dx = tp[3 * k] - x, dy = tp[3 * k + 1] - y, dz = tp[3 * k + 2] - z;
    return dx * dx + dy * dy + dz * dz;
}

// the KC nearest targets of (x, y, z): sorted squared distances d[] (INFINITY: none) and
// sorted-target indices j[] (-1: none)
static void grid_knn(__global const double *tp, __global const int *colstart, long nx,
                     long ny, double x0, double y0, double h, double x, double y, double z,
                     double *d, int *j)
{
    for (int m = 0; m < KC; m++) {
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
            if (lb > 0.0 && lb * lb > d[KC - 1]) break;
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
                    if (dk < d[KC - 1] || (dk == d[KC - 1] && k < j[KC - 1])) {
                        int m = KC - 1;
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
    double x = q[3 * i] + centres[3 * c];
    double y = q[3 * i + 1] + centres[3 * c + 1];
    double z = q[3 * i + 2] + centres[3 * c + 2];
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
        grid_knn(tp, colstart, nx, ny, x0, y0, h, x, y, z, d, jj);
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
    out[i] = j >= 0 ? perm[j] : -1;
}
