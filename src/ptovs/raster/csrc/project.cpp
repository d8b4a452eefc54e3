// Compiled projection and tile binning for ptovs.raster (maths: docs/rasterizer.md §1, §2).
//
// Plain C ABI (ctypes), compiled into the same library as composite.cpp.
//
// ptovs_project_fwd / ptovs_project_bwd mirror `_common.project` line by line: the same
// constants, the same culling rules and the same outputs for culled Gaussians, and the
// backward is the exact VJP of that torch graph (torch.where sends nothing to the branch
// it did not take, torch.clamp passes the gradient on [lo, hi] inclusive, a clamped
// Jacobian axis sends its gradient into z only). The per-Gaussian 3x3 algebra runs in
// double and is rounded to float32 once, at the outputs. Decisions that torch takes on
// float32 values (near/far on z, det finite, the ceil of the radius, the on-image test)
// are taken on the float32-rounded values here, so they agree with torch except where
// torch's own float32 rounding sits on the edge (a radius ceil within an ulp of an
// integer). The backward recomputes the forward per Gaussian (nothing is saved) and a
// Gaussian whose every cotangent is zero gets exactly zero gradients (no 0 * inf NaN).
//
// ptovs_intersect_count / ptovs_intersect_fill reproduce `_common.intersect`
// bit-identically: the binned Gaussians are sorted once by (float32 depth key, id) with
// a stable radix sort, then scattered in that order into their tiles (per-thread
// counts over contiguous ranges of the sorted order, a (tile, thread) prefix sum), so
// every tile list comes out sorted without a per-tile sort.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

// docs/rasterizer.md §5, as in _common.py.
constexpr double kEps2d = 0.3;
constexpr float kEps2dF = 0.3f;  // torch adds EPS2D to a float32 tensor in float32
constexpr float kExtendF = 3.33f;  // GAUSSIAN_EXTEND times a float32 tensor
constexpr double kMinComp2 = 0.005 * 0.005;
constexpr double kDetClamp = 1e-10;
constexpr double kQuatEps2 = 1e-12 * 1e-12;
constexpr double kMaxRadius = 2147483647.0;

// Camera constants, packed by _cpu.py as float64 [20].
struct Cam {
  double R[9], t[3];
  double fx, fy, cx, cy;
  double lim_xp, lim_xn, lim_yp, lim_yn;
  float nearf, farf;
  int width, height;
  bool antialias;
};

Cam unpack(const double* p, int width, int height, int antialias) {
  Cam c;
  for (int k = 0; k < 9; ++k) c.R[k] = p[k];
  for (int k = 0; k < 3; ++k) c.t[k] = p[9 + k];
  c.fx = p[12];
  c.fy = p[13];
  c.cx = p[14];
  c.cy = p[15];
  c.lim_xp = p[16];
  c.lim_xn = p[17];
  c.lim_yp = p[18];
  c.lim_yn = p[19];
  c.nearf = (float)p[20];  // torch compares the float32 z with float32 near / far
  c.farf = (float)p[21];
  c.width = width;
  c.height = height;
  c.antialias = antialias != 0;
  return c;
}

// Every intermediate of the forward that the backward needs.
struct Fwd {
  double rs, ss;      // 1 / sqrt(max(|q|^2, eps^2)) and |q|^2
  double q[4];        // raw quaternion (wxyz)
  double qn[4];       // normalised
  double Rq[9];       // R(qn)
  double s[3];
  double P[9];        // R_cw R(q) diag(s)
  double x, y, z;     // camera-frame mean
  bool in_depth;
  double zs, inv_z;
  double rx, ry;      // x inv_z, y inv_z (before the clamp)
  double clx, cly;    // clamped
  double tx, ty;
  double J00, J02, J11, J12;
  double T[6];        // J P (2 x 3)
  double c00, c01, c11, c00p, c11p, det_orig, det;
  bool valid;
  double w_det, inv_det;  // where(valid, det, 1) and 1 / max(w_det, 1e-10)
  double ratio, comp;     // antialias only
  float u, v;
};

inline void forward_one(const Cam& c, const float* means, const float* quats,
                        const float* scales, int64_t i, Fwd& f) {
  for (int k = 0; k < 4; ++k) f.q[k] = quats[4 * i + k];
  f.ss = f.q[0] * f.q[0] + f.q[1] * f.q[1] + f.q[2] * f.q[2] + f.q[3] * f.q[3];
  f.rs = 1.0 / std::sqrt(std::max(f.ss, kQuatEps2));
  for (int k = 0; k < 4; ++k) f.qn[k] = f.q[k] * f.rs;
  const double w = f.qn[0], x = f.qn[1], y = f.qn[2], z = f.qn[3];
  double* R = f.Rq;
  R[0] = 1 - 2 * (y * y + z * z);
  R[1] = 2 * (x * y - w * z);
  R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z);
  R[4] = 1 - 2 * (x * x + z * z);
  R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y);
  R[7] = 2 * (y * z + w * x);
  R[8] = 1 - 2 * (x * x + y * y);
  for (int k = 0; k < 3; ++k) f.s[k] = scales[3 * i + k];
  // P = R_cw M, M = R diag(s); Sigma_c = P P^T.
  for (int r = 0; r < 3; ++r)
    for (int j = 0; j < 3; ++j)
      f.P[3 * r + j] = (c.R[3 * r] * R[j] + c.R[3 * r + 1] * R[3 + j] +
                        c.R[3 * r + 2] * R[6 + j]) * f.s[j];
  const double mx = means[3 * i], my = means[3 * i + 1], mz = means[3 * i + 2];
  f.x = c.R[0] * mx + c.R[1] * my + c.R[2] * mz + c.t[0];
  f.y = c.R[3] * mx + c.R[4] * my + c.R[5] * mz + c.t[1];
  f.z = c.R[6] * mx + c.R[7] * my + c.R[8] * mz + c.t[2];
  const float zf = (float)f.z;
  f.in_depth = zf > c.nearf && zf < c.farf;
  f.zs = f.in_depth ? f.z : 1.0;
  f.inv_z = 1.0 / f.zs;
  f.rx = f.x * f.inv_z;
  f.ry = f.y * f.inv_z;
  f.clx = std::min(std::max(f.rx, -c.lim_xn), c.lim_xp);
  f.cly = std::min(std::max(f.ry, -c.lim_yn), c.lim_yp);
  f.tx = f.zs * f.clx;
  f.ty = f.zs * f.cly;
  f.J00 = c.fx * f.inv_z;
  f.J02 = -c.fx * f.tx * f.inv_z * f.inv_z;
  f.J11 = c.fy * f.inv_z;
  f.J12 = -c.fy * f.ty * f.inv_z * f.inv_z;
  for (int j = 0; j < 3; ++j) {
    f.T[j] = f.J00 * f.P[j] + f.J02 * f.P[6 + j];
    f.T[3 + j] = f.J11 * f.P[3 + j] + f.J12 * f.P[6 + j];
  }
  const double* T = f.T;
  f.c00 = T[0] * T[0] + T[1] * T[1] + T[2] * T[2];
  f.c01 = T[0] * T[3] + T[1] * T[4] + T[2] * T[5];
  f.c11 = T[3] * T[3] + T[4] * T[4] + T[5] * T[5];
  f.det_orig = f.c00 * f.c11 - f.c01 * f.c01;
  f.c00p = f.c00 + kEps2d;
  f.c11p = f.c11 + kEps2d;
  f.det = f.c00p * f.c11p - f.c01 * f.c01;
  const float detf = (float)f.det;  // torch tests the float32 det (inf / NaN: culled)
  f.valid = f.in_depth && detf > 0.0f && std::isfinite(detf);
  f.w_det = f.valid ? f.det : 1.0;
  f.inv_det = 1.0 / std::max(f.w_det, kDetClamp);
  if (c.antialias) {
    f.ratio = (f.valid ? f.det_orig : 1.0) * f.inv_det;
    f.comp = std::sqrt(std::max(f.ratio, kMinComp2));
  }
  f.u = (float)(c.fx * f.x * f.inv_z + c.cx);
  f.v = (float)(c.fy * f.y * f.inv_z + c.cy);
}

// ceil(3.33 sqrt(max(c + 0.3, 0))) as torch computes it: float32 until the ceil.
inline double radius_of(double c) {
  const float cp = (float)c + kEps2dF;
  const float ext = kExtendF * std::sqrt(std::max(cp, 0.0f));  // NaN stays NaN
  if (std::isnan(ext)) return 0.0;  // nan_to_num(0)
  return std::min(std::max(std::ceil((double)ext), 0.0), kMaxRadius);
}

// wR (grad of R(qn)) -> grad of qn.
inline void rotmat_vjp(const double* q, const double* G, double* vq) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  vq[0] = 2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
  vq[1] = 2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] +
               w * G[7] - 2 * x * G[8]);
  vq[2] = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] +
               z * G[7] - 2 * y * G[8]);
  vq[3] = 2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] +
               x * G[6] + y * G[7]);
}

inline float at(const float* p, int64_t k) { return p ? p[k] : 0.0f; }

// Order-preserving uint32 key of a float32 (as `_common._depth_sort_key`).
inline uint64_t depth_key(float d) {
  int32_t bits;
  std::memcpy(&bits, &d, sizeof bits);
  const int64_t b = bits;
  return (uint64_t)(b >= 0 ? b + 2147483648LL : 2147483647LL - (b & 0x7FFFFFFF));
}

struct Box {
  int32_t x0, x1, y0, y1;  // empty when x1 <= x0 or y1 <= y0
};

inline int32_t clamp_grid(double v, int32_t hi) {
  if (!(v > 0.0)) return 0;  // NaN -> 0
  return v >= (double)hi ? hi : (int32_t)v;
}

inline Box box_of(const float* means2d, const int32_t* radii, int64_t i, int tw, int th,
                  int tile) {
  Box b{0, 0, 0, 0};
  const int32_t rx = radii[2 * i], ry = radii[2 * i + 1];
  if (!(rx > 0 && ry > 0)) return b;
  const double u = means2d[2 * i], v = means2d[2 * i + 1];
  b.x0 = clamp_grid(std::floor((u - rx) / tile), tw);
  b.x1 = clamp_grid(std::ceil((u + rx) / tile), tw);
  b.y0 = clamp_grid(std::floor((v - ry) / tile), th);
  b.y1 = clamp_grid(std::ceil((v + ry) / tile), th);
  return b;
}

inline int64_t box_count(const Box& b) {
  if (b.x1 <= b.x0 || b.y1 <= b.y0) return 0;
  return (int64_t)(b.x1 - b.x0) * (b.y1 - b.y0);
}

inline int thread_id() {
#ifdef _OPENMP
  return omp_get_thread_num();
#else
  return 0;
#endif
}

inline int num_threads() {
#ifdef _OPENMP
  return omp_get_num_threads();
#else
  return 1;
#endif
}

inline int64_t chunk_lo(int64_t n, int nt, int k) { return n * k / nt; }

}  // namespace

extern "C" {

// Projection forward. cam: float64 [22] = R_cw (9, row-major), t (3), fx, fy, cx, cy,
// lim_xp, lim_xn, lim_yp, lim_yn, near, far. Outputs: means2d [N, 2], conics [N, 3],
// opac_out [N] (opacity times the compensation when antialiasing, else a copy),
// depths [N], radii [N, 2] int32.
int ptovs_project_fwd(const float* means, const float* quats, const float* scales,
                      const float* opac, int64_t n, const double* cam, int width,
                      int height, int antialias, float* means2d, float* conics,
                      float* opac_out, float* depths, int32_t* radii, int nt) {
  const Cam c = unpack(cam, width, height, antialias);
#pragma omp parallel for num_threads(nt) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    Fwd f;
    forward_one(c, means, quats, scales, i, f);
    means2d[2 * i] = f.u;
    means2d[2 * i + 1] = f.v;
    conics[3 * i] = (float)(f.c11p * f.inv_det);
    conics[3 * i + 1] = (float)(-f.c01 * f.inv_det);
    conics[3 * i + 2] = (float)(f.c00p * f.inv_det);
    opac_out[i] = antialias ? (float)(opac[i] * f.comp) : opac[i];
    depths[i] = (float)f.z;
    const double r0 = radius_of(f.c00), r1 = radius_of(f.c11);
    const double u = f.u, v = f.v;
    const bool inside = (u + r0 > 0) && (u - r0 < width) && (v + r1 > 0) && (v - r1 < height);
    const bool keep = f.valid && inside && r0 > 0 && r1 > 0;
    radii[2 * i] = keep ? (int32_t)r0 : 0;
    radii[2 * i + 1] = keep ? (int32_t)r1 : 0;
  }
  return 0;
}

// Projection backward: the VJP of ptovs_project_fwd (of `_common.project`) for the
// cotangents v_means2d [N, 2], v_conics [N, 3], v_opac [N], v_depths [N] (any may be
// null: zero). Writes v_means [N, 3], v_quats [N, 4], v_scales [N, 3], v_opac_in [N].
int ptovs_project_bwd(const float* means, const float* quats, const float* scales,
                      const float* opac, int64_t n, const double* cam, int width,
                      int height, int antialias, const float* g_means2d,
                      const float* g_conics, const float* g_opac, const float* g_depths,
                      float* v_means, float* v_quats, float* v_scales, float* v_opac_in,
                      int nt) {
  const Cam c = unpack(cam, width, height, antialias);
#pragma omp parallel for num_threads(nt) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    const double gu = at(g_means2d, 2 * i), gv = at(g_means2d, 2 * i + 1);
    const double ga = at(g_conics, 3 * i), gb = at(g_conics, 3 * i + 1),
                 gc = at(g_conics, 3 * i + 2);
    const double go = at(g_opac, i), gz = at(g_depths, i);
    if (gu == 0 && gv == 0 && ga == 0 && gb == 0 && gc == 0 && go == 0 && gz == 0) {
      for (int k = 0; k < 3; ++k) v_means[3 * i + k] = v_scales[3 * i + k] = 0.0f;
      for (int k = 0; k < 4; ++k) v_quats[4 * i + k] = 0.0f;
      v_opac_in[i] = 0.0f;
      continue;
    }
    Fwd f;
    forward_one(c, means, quats, scales, i, f);

    // opacities_out = o * comp (antialias) or o.
    double v_inv_det = 0.0, v_det_orig = 0.0;
    if (antialias) {
      v_opac_in[i] = (float)(go * f.comp);
      const double v_comp = go * opac[i];
      const double v_ratio = f.ratio >= kMinComp2 ? v_comp / (2.0 * f.comp) : 0.0;
      const double w_do = f.valid ? f.det_orig : 1.0;
      v_inv_det += v_ratio * w_do;
      if (f.valid) v_det_orig = v_ratio * f.inv_det;
    } else {
      v_opac_in[i] = (float)go;
    }

    // conics = (c11p, -c01, c00p) * inv_det.
    double v_c00p = gc * f.inv_det, v_c11p = ga * f.inv_det, v_c01 = -gb * f.inv_det;
    v_inv_det += ga * f.c11p - gb * f.c01 + gc * f.c00p;
    const double v_w = f.w_det >= kDetClamp ? -f.inv_det * f.inv_det * v_inv_det : 0.0;
    const double v_det = f.valid ? v_w : 0.0;
    v_c00p += f.c11p * v_det;
    v_c11p += f.c00p * v_det;
    v_c01 -= 2.0 * f.c01 * v_det;
    double v_c00 = v_c00p + f.c11 * v_det_orig;
    double v_c11 = v_c11p + f.c00 * v_det_orig;
    v_c01 -= 2.0 * f.c01 * v_det_orig;

    // cov2d = T T^T, T = J P.
    const double* T = f.T;
    double vT[6];
    for (int j = 0; j < 3; ++j) {
      vT[j] = 2.0 * v_c00 * T[j] + v_c01 * T[3 + j];
      vT[3 + j] = v_c01 * T[j] + 2.0 * v_c11 * T[3 + j];
    }
    double vP[9];
    for (int j = 0; j < 3; ++j) {
      vP[j] = f.J00 * vT[j];
      vP[3 + j] = f.J11 * vT[3 + j];
      vP[6 + j] = f.J02 * vT[j] + f.J12 * vT[3 + j];
    }
    const double vJ00 = vT[0] * f.P[0] + vT[1] * f.P[1] + vT[2] * f.P[2];
    const double vJ02 = vT[0] * f.P[6] + vT[1] * f.P[7] + vT[2] * f.P[8];
    const double vJ11 = vT[3] * f.P[3] + vT[4] * f.P[4] + vT[5] * f.P[5];
    const double vJ12 = vT[3] * f.P[6] + vT[4] * f.P[7] + vT[5] * f.P[8];

    // J = [[fx inv_z, 0, -fx tx inv_z^2], [0, fy inv_z, -fy ty inv_z^2]].
    double vx = 0.0, vy = 0.0, v_zs = 0.0;
    double vinvz = c.fx * vJ00 + c.fy * vJ11 - 2.0 * c.fx * f.tx * f.inv_z * vJ02 -
                   2.0 * c.fy * f.ty * f.inv_z * vJ12;
    const double vtx = -c.fx * f.inv_z * f.inv_z * vJ02;
    const double vty = -c.fy * f.inv_z * f.inv_z * vJ12;
    // tx = zs clamp(x inv_z): a clamped axis sends its gradient into z only.
    v_zs += f.clx * vtx + f.cly * vty;
    if (f.rx >= -c.lim_xn && f.rx <= c.lim_xp) {
      const double g = f.zs * vtx;
      vx += f.inv_z * g;
      vinvz += f.x * g;
    }
    if (f.ry >= -c.lim_yn && f.ry <= c.lim_yp) {
      const double g = f.zs * vty;
      vy += f.inv_z * g;
      vinvz += f.y * g;
    }
    // means2d = (fx x inv_z + cx, fy y inv_z + cy).
    vx += c.fx * f.inv_z * gu;
    vy += c.fy * f.inv_z * gv;
    vinvz += c.fx * f.x * gu + c.fy * f.y * gv;
    v_zs -= f.inv_z * f.inv_z * vinvz;
    const double vz = (f.in_depth ? v_zs : 0.0) + gz;

    // mean_c = R_cw mean + t.
    for (int k = 0; k < 3; ++k)
      v_means[3 * i + k] = (float)(c.R[k] * vx + c.R[3 + k] * vy + c.R[6 + k] * vz);

    // P = R_cw M, M = R(qn) diag(s).
    double vR[9];
    double vs[3] = {0.0, 0.0, 0.0};
    for (int r = 0; r < 3; ++r)
      for (int j = 0; j < 3; ++j) {
        const double vM = c.R[r] * vP[j] + c.R[3 + r] * vP[3 + j] + c.R[6 + r] * vP[6 + j];
        vR[3 * r + j] = vM * f.s[j];
        vs[j] += vM * f.Rq[3 * r + j];
      }
    for (int k = 0; k < 3; ++k) v_scales[3 * i + k] = (float)vs[k];
    double vqn[4];
    rotmat_vjp(f.qn, vR, vqn);
    // qn = q rsqrt(clamp_min(|q|^2, eps^2)).
    double dot = 0.0;
    for (int k = 0; k < 4; ++k) dot += vqn[k] * f.q[k];
    const double k2 = f.ss >= kQuatEps2 ? f.rs * f.rs * f.rs * dot : 0.0;
    for (int k = 0; k < 4; ++k) v_quats[4 * i + k] = (float)(f.rs * vqn[k] - k2 * f.q[k]);
  }
  return 0;
}

// Tile binning, pass 1. Scratch kept for pass 2: boxes [N, 4] int32, order [N] int32
// (the binned Gaussians sorted by float32 depth, ties by id; *n_valid of them) and
// counts [nt, n_tiles] int32 (per-thread write cursors). Writes tile_offsets
// [n_tiles + 1] and *m (the number of entries). Returns 2 when out of memory and 3
// when the entries exceed int32 offsets.
int ptovs_intersect_count(const float* means2d, const int32_t* radii, const float* depths,
                          int64_t n, int tw, int th, int tile, int32_t* boxes,
                          int32_t* order, int64_t* n_valid, int32_t* counts,
                          int32_t* tile_offsets, int64_t* m, int nt) {
  const int64_t n_tiles = (int64_t)tw * th;
  if (nt < 1) nt = 1;
#pragma omp parallel for num_threads(nt) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    const Box b = box_of(means2d, radii, i, tw, th, tile);
    std::memcpy(boxes + 4 * i, &b, sizeof b);
  }
  // Stable LSD radix sort of the binned ids (ascending) by depth key: (key, id) order.
  uint32_t* key = static_cast<uint32_t*>(std::malloc(sizeof(uint32_t) * 2 * std::max<int64_t>(n, 1)));
  int32_t* tmp = static_cast<int32_t*>(std::malloc(sizeof(int32_t) * std::max<int64_t>(n, 1)));
  if (!key || !tmp) {
    std::free(key);
    std::free(tmp);
    return 2;
  }
  uint32_t* key2 = key + n;
  int64_t v = 0;
  for (int64_t i = 0; i < n; ++i) {
    Box b;
    std::memcpy(&b, boxes + 4 * i, sizeof b);
    if (box_count(b) == 0) continue;
    order[v] = (int32_t)i;
    key[v++] = (uint32_t)depth_key(depths[i]);
  }
  {
    int32_t* src = order;
    int32_t* dst = tmp;
    uint32_t* ksrc = key;
    uint32_t* kdst = key2;
    constexpr int kBits = 11, kBuckets = 1 << kBits;
    int64_t hist[kBuckets];
    for (int shift = 0; shift < 32; shift += kBits) {
      std::fill(hist, hist + kBuckets, 0);
      for (int64_t j = 0; j < v; ++j) ++hist[(ksrc[j] >> shift) & (kBuckets - 1)];
      if (v == 0 || hist[(ksrc[0] >> shift) & (kBuckets - 1)] == v) continue;  // one digit
      int64_t run = 0;
      for (int k = 0; k < kBuckets; ++k) {
        const int64_t c = hist[k];
        hist[k] = run;
        run += c;
      }
      for (int64_t j = 0; j < v; ++j) {
        const int64_t pos = hist[(ksrc[j] >> shift) & (kBuckets - 1)]++;
        dst[pos] = src[j];
        kdst[pos] = ksrc[j];
      }
      std::swap(src, dst);
      std::swap(ksrc, kdst);
    }
    if (src != order) std::memcpy(order, src, sizeof(int32_t) * v);
  }
  std::free(key);
  std::free(tmp);
  *n_valid = v;

  // Per-thread tile counts over contiguous ranges of the sorted order.
#pragma omp parallel num_threads(nt)
  {
    for (int k = thread_id(); k < nt; k += num_threads()) {
      int32_t* cnt = counts + (int64_t)k * n_tiles;
      std::fill(cnt, cnt + n_tiles, 0);
      for (int64_t j = chunk_lo(v, nt, k); j < chunk_lo(v, nt, k + 1); ++j) {
        Box b;
        std::memcpy(&b, boxes + 4 * (int64_t)order[j], sizeof b);
        for (int32_t ty = b.y0; ty < b.y1; ++ty)
          for (int32_t tx = b.x0; tx < b.x1; ++tx) ++cnt[(int64_t)ty * tw + tx];
      }
    }
  }
  // Exclusive prefix over (tile, thread): counts become each thread's write cursors.
  int64_t run = 0;
  for (int64_t t = 0; t < n_tiles; ++t) {
    if (run > std::numeric_limits<int32_t>::max()) return 3;
    tile_offsets[t] = (int32_t)run;
    for (int k = 0; k < nt; ++k) {
      int32_t* cnt = counts + (int64_t)k * n_tiles + t;
      const int64_t c = *cnt;
      *cnt = (int32_t)run;
      run += c;
    }
  }
  if (run > std::numeric_limits<int32_t>::max()) return 3;
  tile_offsets[n_tiles] = (int32_t)run;
  *m = run;
  return 0;
}

// Tile binning, pass 2 (the same n_valid, order, boxes, counts and nt as pass 1):
// scatters the depth-sorted ids into their tiles, so each tile lists its Gaussians
// front to back by float32 depth, ties by id. Writes flatten_ids [M].
int ptovs_intersect_fill(int64_t n_valid, const int32_t* order, const int32_t* boxes,
                         int32_t* counts, int tw, int th, int32_t* flatten_ids, int nt) {
  const int64_t n_tiles = (int64_t)tw * th;
  if (nt < 1) nt = 1;
#pragma omp parallel num_threads(nt)
  {
    for (int k = thread_id(); k < nt; k += num_threads()) {
      int32_t* cur = counts + (int64_t)k * n_tiles;
      for (int64_t j = chunk_lo(n_valid, nt, k); j < chunk_lo(n_valid, nt, k + 1); ++j) {
        const int32_t id = order[j];
        Box b;
        std::memcpy(&b, boxes + 4 * (int64_t)id, sizeof b);
        for (int32_t ty = b.y0; ty < b.y1; ++ty)
          for (int32_t tx = b.x0; tx < b.x1; ++tx)
            flatten_ids[cur[(int64_t)ty * tw + tx]++] = id;
      }
    }
  }
  return 0;
}

}  // extern "C"
