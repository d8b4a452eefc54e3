// Compiled CPU compositing for ptovs.raster (maths: docs/rasterizer.md §3, §4, §9).
//
// Plain C ABI, loaded with ctypes: no torch or pybind11 headers, so a cold build takes
// a few seconds and ctypes releases the GIL for the duration of a call.
//
// Layout: "Gaussian outer, pixel inner". A thread takes a whole tile (OpenMP, dynamic),
// keeps the per-pixel state (T, accumulators, done mask, last contributor) in small
// arrays, and walks the tile's depth-sorted list once; for each Gaussian it updates every
// pixel of the tile inside the Gaussian's opacity-aware bounding box, 8 pixels per SIMD
// vector (one tile row is ceil(tile / 8) vectors, padded lanes are permanently done).
// The backward pass walks the list back to front with per-pixel T recovery, reduces the
// per-Gaussian gradient over the tile's pixels in registers and adds it once per
// (tile, Gaussian) into a per-thread buffer [threads, N, 6 + D] summed by the caller.
//
// Forward and backward recompute sigma and alpha with the same inline code, explicit
// FMAs and no -ffast-math, so their skip/stop decisions are bit-identical.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>

#ifdef _OPENMP
#include <omp.h>
#endif

#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#define PTOVS_AVX2 1
#else
#define PTOVS_AVX2 0
#endif

namespace {

// docs/rasterizer.md §5.
constexpr float kAlphaThreshold = 1.0f / 255.0f;
constexpr float kMaxAlpha = 0.99f;
constexpr float kTransmittanceThreshold = 1e-4f;
constexpr float kMinOneMinusAlpha = 1e-6f;
// Pre-exp cull: sigma > ln(255 o) + 1e-3 implies alpha < 1/255 with margin to spare.
constexpr float kCullMargin = 1e-3f;

constexpr int L = 8;  // lanes per vector
constexpr int kPrefetch = 4;  // tile-list entries to prefetch ahead
typedef float vf __attribute__((vector_size(32)));
typedef int32_t vi __attribute__((vector_size(32)));

inline vf splat(float x) { return vf{x, x, x, x, x, x, x, x}; }
inline vi splati(int32_t x) { return vi{x, x, x, x, x, x, x, x}; }
inline vf ldf(const float* p) {
  vf r;
  std::memcpy(&r, p, sizeof r);
  return r;
}
inline void stf(float* p, vf x) { std::memcpy(p, &x, sizeof x); }
inline vi ldi(const int32_t* p) {
  vi r;
  std::memcpy(&r, p, sizeof r);
  return r;
}
inline void sti(int32_t* p, vi x) { std::memcpy(p, &x, sizeof x); }

#if PTOVS_AVX2
inline vf vfma(vf a, vf b, vf c) {
  return (vf)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
}
inline vf sel(vi m, vf a, vf b) {  // m ? a : b
  return (vf)_mm256_blendv_ps((__m256)b, (__m256)a, (__m256)m);
}
inline int mask_bits(vi m) { return _mm256_movemask_ps((__m256)m); }
inline vf vmin(vf a, vf b) { return (vf)_mm256_min_ps((__m256)a, (__m256)b); }
inline vf vmax(vf a, vf b) { return (vf)_mm256_max_ps((__m256)a, (__m256)b); }
inline vf vround(vf x) {
  return (vf)_mm256_round_ps((__m256)x, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
}
inline vi vcvt(vf x) { return (vi)_mm256_cvtps_epi32((__m256)x); }
#else
// Portable fallback (GCC/Clang vector extensions); built with -ffp-contract=off, so
// a * b + c is the same two roundings everywhere it appears.
inline vf vfma(vf a, vf b, vf c) { return a * b + c; }
inline vf sel(vi m, vf a, vf b) { return (vf)(((vi)a & m) | ((vi)b & ~m)); }
inline int mask_bits(vi m) {
  int r = 0;
  for (int l = 0; l < L; ++l) r |= (m[l] < 0) << l;
  return r;
}
inline vf vmin(vf a, vf b) { return sel(a < b, a, b); }
inline vf vmax(vf a, vf b) { return sel(a > b, a, b); }
inline vf vround(vf x) {
  const vf magic = splat(12582912.0f);  // 1.5 * 2^23: round to nearest for |x| < 2^22
  return (x + magic) - magic;
}
inline vi vcvt(vf x) { return __builtin_convertvector(x, vi); }
#endif
inline vi sel_i(vi m, vi a, vi b) { return (a & m) | (b & ~m); }
inline float hsum(vf x) {
  float s = 0.0f;
  for (int l = 0; l < L; ++l) s += x[l];
  return s;
}

// The lane sums of x[0..7], as one vector.
inline vf reduce8(const vf* x) {
#if PTOVS_AVX2
  const __m256 a = _mm256_hadd_ps((__m256)x[0], (__m256)x[1]);
  const __m256 b = _mm256_hadd_ps((__m256)x[2], (__m256)x[3]);
  const __m256 c = _mm256_hadd_ps((__m256)x[4], (__m256)x[5]);
  const __m256 d = _mm256_hadd_ps((__m256)x[6], (__m256)x[7]);
  const __m256 ab = _mm256_hadd_ps(a, b);  // [x0 x1 x2 x3 | x0 x1 x2 x3] half sums
  const __m256 cd = _mm256_hadd_ps(c, d);
  return (vf)_mm256_add_ps(_mm256_permute2f128_ps(ab, cd, 0x20),
                           _mm256_permute2f128_ps(ab, cd, 0x31));
#else
  vf r;
  for (int j = 0; j < L; ++j) r[j] = hsum(x[j]);
  return r;
#endif
}

// exp(x) for x in [-87, 88] (Cephes expf, about 1 ulp); inputs are clamped first so
// masked-out lanes never make inf or NaN.
inline vf vexp(vf x) {
  x = vmin(vmax(x, splat(-87.0f)), splat(88.0f));
  const vf n = vround(x * splat(1.44269504088896341f));
  vf r = vfma(n, splat(-0.693359375f), x);
  r = vfma(n, splat(2.12194440e-4f), r);
  vf p = splat(1.9875691500e-4f);
  p = vfma(p, r, splat(1.3981999507e-3f));
  p = vfma(p, r, splat(8.3334519073e-3f));
  p = vfma(p, r, splat(4.1665795894e-2f));
  p = vfma(p, r, splat(1.6666665459e-1f));
  p = vfma(p, r, splat(5.0000001201e-1f));
  p = vfma(p, r * r, r + splat(1.0f));
  const vi bits = (vcvt(n) + splati(127)) << 23;
  return p * (vf)bits;
}

// Per-Gaussian constants, one cache line each.
struct alignas(64) GParam {
  float u, v;      // mean2d
  float a, b, c;   // conic
  float ha, hc;    // 0.5 a, 0.5 c
  float o;         // opacity
  float thr;       // ln(255 o) + 1e-3; < 0 marks a Gaussian that can never contribute
  float ex, ey;    // half extents of {sigma <= thr}, with margin (inf when unbounded)
  float pad[5];
};

void precompute(const float* means2d, const float* conics, const float* opac,
                int64_t n, GParam* gp, int nt) {
#pragma omp parallel for num_threads(nt) schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    GParam g;
    std::memset(&g, 0, sizeof g);
    g.u = means2d[2 * i];
    g.v = means2d[2 * i + 1];
    g.a = conics[3 * i];
    g.b = conics[3 * i + 1];
    g.c = conics[3 * i + 2];
    g.ha = 0.5f * g.a;
    g.hc = 0.5f * g.c;
    g.o = opac[i];
    g.thr = -1.0f;
    g.ex = g.ey = std::numeric_limits<float>::infinity();
    const bool finite = std::isfinite(g.u) && std::isfinite(g.v) && std::isfinite(g.a) &&
                        std::isfinite(g.b) && std::isfinite(g.c);
    if (finite && g.o > 0.0f) {
      const float thr = std::log(255.0f * g.o) + kCullMargin;
      if (thr >= 0.0f) g.thr = thr;  // NaN (o = inf) stays culled
    }
    if (g.thr >= 0.0f) {
      // min over dx of sigma = 0.5 dy^2 det / a, so sigma <= thr needs
      // |dy| <= sqrt(2 thr a / det) (and |dx| <= sqrt(2 thr c / det)). The margins
      // cover float rounding of sigma; they only cost a few wasted lanes.
      const double a = g.a, b = g.b, c = g.c;
      const double det = a * c - b * b;
      if (a > 0.0 && c > 0.0 && det > 1e-30 * a * c) {
        const double t = 2.0 * (g.thr * (1.0 + 1e-3) + 1e-3) / det;
        g.ex = (float)(std::sqrt(t * c) * (1.0 + 1e-4) + 1e-2);
        g.ey = (float)(std::sqrt(t * a) * (1.0 + 1e-4) + 1e-2);
      }
    }
    gp[i] = g;
  }
}

struct Tile {
  int x0, y0;      // pixel origin
  int rows, cols;  // valid rows / columns (edge tiles are cut by the image)
  int nvec, rs;    // vectors per row, row stride in floats (nvec * L)
  int npix;        // tile * rs
};

inline Tile make_tile(int t, int tw, int tile, int width, int height) {
  Tile g;
  g.x0 = (t % tw) * tile;
  g.y0 = (t / tw) * tile;
  g.rows = std::min(tile, height - g.y0);
  g.cols = std::min(tile, width - g.x0);
  g.nvec = (tile + L - 1) / L;
  g.rs = g.nvec * L;
  g.npix = tile * g.rs;
  return g;
}

// Rows [ly0, ly1] and vectors [k0, k1] of the tile that the bounding box touches.
inline bool box(const GParam& g, const Tile& t, int& ly0, int& ly1, int& k0, int& k1) {
  const float cy = g.v - ((float)t.y0 + 0.5f);
  const float cx = g.u - ((float)t.x0 + 0.5f);
  // Clamped to [-1, rows] before the int casts (far-away means would overflow them).
  const float ry = (float)t.rows, rx = (float)t.cols;
  const float fy0 = std::min(std::max(cy - g.ey, -1.0f), ry);
  const float fy1 = std::max(std::min(cy + g.ey, ry), -1.0f);
  const float fx0 = std::min(std::max(cx - g.ex, -1.0f), rx);
  const float fx1 = std::max(std::min(cx + g.ex, rx), -1.0f);
  ly0 = std::max(0, (int)std::ceil(fy0));
  ly1 = std::min(t.rows - 1, (int)std::floor(fy1));
  const int lx0 = std::max(0, (int)std::ceil(fx0));
  const int lx1 = std::min(t.cols - 1, (int)std::floor(fx1));
  k0 = lx0 / L;
  k1 = lx1 / L;
  return ly0 <= ly1 && lx0 <= lx1;
}

// Row constants for sigma = (0.5 a dx + b dy) dx + 0.5 c dy^2.
struct Row {
  float dy, bdy, hcdy2;
};
inline Row row_of(const GParam& g, const Tile& t, int ly) {
  Row r;
  r.dy = g.v - ((float)(t.y0 + ly) + 0.5f);
  r.bdy = g.b * r.dy;
  r.hcdy2 = g.hc * r.dy * r.dy;
  return r;
}
inline vf sigma_of(const GParam& g, const Row& r, vf dx) {
  return vfma(vfma(splat(g.ha), dx, splat(r.bdy)), dx, splat(r.hcdy2));
}
// Candidate mask before the exp: sigma >= 0 and the pre-exp cull.
inline vi sigma_ok(const GParam& g, vf sig) {
  return (vi)(sig >= splat(0.0f)) & (vi)(sig <= splat(g.thr));
}

GParam* alloc_params(int64_t n) {
  return static_cast<GParam*>(std::aligned_alloc(64, std::max<int64_t>(n, 1) * sizeof(GParam)));
}

float* falloc(size_t n) {
  void* p = nullptr;
  if (posix_memalign(&p, 64, std::max<size_t>(n, 1) * sizeof(float)) != 0) return nullptr;
  return static_cast<float*>(p);
}

// Backward's gradient slices: fixed, so the order of its sums does not follow the
// thread count (backward_tiles).
constexpr int kGradSlices = 16;

int thread_id() {
#ifdef _OPENMP
  return omp_get_thread_num();
#else
  return 0;
#endif
}

// Forward over all tiles. Optional outputs may be null. With rowptr/out_ids/out_w set,
// every composited pair is also written in CSR row order (pixel-major, front to back):
// rowptr must then be the exclusive prefix sum of this same pass's contributor counts.
template <int DT>  // DT > 0: the channel count, known at compile time; 0: runtime d_
int forward_tiles(const GParam* gp, const float* colors, const int d_, const float* bg,
                  const int32_t* tile_offsets, const int32_t* flatten_ids, int tw, int th,
                  int tile, int width, int height, float* image, float* alpha_out,
                  float* t_final, int32_t* n_contrib, int32_t* last_out,
                  const int64_t* rowptr, int32_t* out_ids, float* out_w, int nt) {
  const int d = DT > 0 ? DT : d_;
  const int n_tiles = tw * th;
  const bool emit = out_ids != nullptr;
  int failed = 0;
  // firstprivate: locals of the outlined region, so stores through float pointers
  // cannot force reloads of them.
#pragma omp parallel num_threads(nt) reduction(| : failed) \
    firstprivate(gp, colors, d, bg, tile_offsets, flatten_ids, tw, tile, width, height, \
                 image, alpha_out, t_final, n_contrib, last_out, rowptr, out_ids, out_w, emit)
  {
    const Tile t0 = make_tile(0, tw, tile, width, height);
    const int npix = t0.npix;
    float* tt = falloc(npix);
    float* acc = falloc((size_t)npix * std::max(d, 1));
    int32_t* act = reinterpret_cast<int32_t*>(falloc(npix));
    int32_t* cnt = reinterpret_cast<int32_t*>(falloc(npix));
    int32_t* last = reinterpret_cast<int32_t*>(falloc(npix));
    float* colx = falloc(t0.rs);
    if (!tt || !acc || !act || !cnt || !last || !colx) {
      failed = 1;
    }
#pragma omp for schedule(dynamic, 1)
    for (int ti = 0; ti < n_tiles; ++ti) {
      if (failed) continue;  // no scratch memory: every thread still reaches the loop
      const Tile t = make_tile(ti, tw, tile, width, height);
      int n_active = t.rows * t.cols;
      for (int ly = 0; ly < tile; ++ly)
        for (int lx = 0; lx < t.rs; ++lx) {
          const int p = ly * t.rs + lx;
          tt[p] = 1.0f;
          act[p] = (ly < t.rows && lx < t.cols) ? -1 : 0;
          cnt[p] = 0;
          last[p] = -1;
        }
      std::fill(acc, acc + (size_t)npix * d, 0.0f);
      for (int lx = 0; lx < t.rs; ++lx) colx[lx] = (float)(t.x0 + lx) + 0.5f;

      const int32_t start = tile_offsets[ti], end = tile_offsets[ti + 1];
      for (int32_t idx = start; idx < end && n_active > 0; ++idx) {
        if (idx + kPrefetch < end) __builtin_prefetch(gp + flatten_ids[idx + kPrefetch]);
        const int32_t gid = flatten_ids[idx];
        const GParam& g = gp[gid];
        if (!(g.thr >= 0.0f)) continue;
        int ly0, ly1, k0, k1;
        if (!box(g, t, ly0, ly1, k0, k1)) continue;
        const float* col = colors + (int64_t)gid * d;
        const vf vu = splat(g.u), vo = splat(g.o);
        for (int ly = ly0; ly <= ly1; ++ly) {
          const Row r = row_of(g, t, ly);
          for (int k = k0; k <= k1; ++k) {
            const int p = ly * t.rs + k * L;
            const vi a = ldi(act + p);
            const vf dx = vu - ldf(colx + k * L);
            const vf sig = sigma_of(g, r, dx);
            // One early branch, on the cheap sigma test; past it, everything is
            // branch-free (a late, data-dependent branch after the exp costs more
            // when mispredicted than the work it would skip; measured).
            const vi m0 = a & sigma_ok(g, sig);
            if (!mask_bits(m0)) continue;
            const vf e = vexp(-sig);
            const vf al = vmin(vo * e, splat(kMaxAlpha));
            const vi m = m0 & (vi)(al >= splat(kAlphaThreshold));
            const vf tv = ldf(tt + p);
            const vf next_t = tv * (splat(1.0f) - al);
            // Exclusive stop: that Gaussian is not composited.
            const vi stop = m & (vi)(next_t <= splat(kTransmittanceThreshold));
            const vi c = m & ~stop;
            if (const int sb = mask_bits(stop)) {
              sti(act + p, a & ~stop);
              n_active -= __builtin_popcount(sb);
            }
            const vf w = sel(c, al * tv, splat(0.0f));
            stf(tt + p, sel(c, next_t, tv));
            const vi cnt_before = ldi(cnt + p);
            sti(cnt + p, cnt_before - c);  // c lanes are -1
            sti(last + p, sel_i(c, splati(idx), ldi(last + p)));
            float* ap = acc + p;
            for (int j = 0; j < d; ++j, ap += npix) stf(ap, vfma(splat(col[j]), w, ldf(ap)));
            if (emit) {
              const int cb = mask_bits(c);
              const int64_t pg0 = (int64_t)(t.y0 + ly) * width + t.x0 + k * L;
              for (int bits = cb; bits; bits &= bits - 1) {
                const int l = __builtin_ctz(bits);
                const int64_t pos = rowptr[pg0 + l] + cnt_before[l];
                out_ids[pos] = gid;
                out_w[pos] = w[l];
              }
            }
          }
        }
      }

      for (int ly = 0; ly < t.rows; ++ly)
        for (int lx = 0; lx < t.cols; ++lx) {
          const int p = ly * t.rs + lx;
          const int64_t pg = (int64_t)(t.y0 + ly) * width + t.x0 + lx;
          const float tf = tt[p];
          if (image) {
            float* out = image + pg * d;
            for (int j = 0; j < d; ++j) {
              float v = acc[(size_t)j * npix + p];
              if (bg) v += tf * bg[j];
              out[j] = v;
            }
          }
          if (alpha_out) alpha_out[pg] = 1.0f - tf;
          if (t_final) t_final[pg] = tf;
          if (n_contrib) n_contrib[pg] = cnt[p];
          if (last_out) last_out[pg] = last[p];
        }
    }
    free(tt);
    free(acc);
    free(act);
    free(cnt);
    free(last);
    free(colx);
  }
  return failed ? 2 : 0;
}


// Backward over all tiles (docs/rasterizer.md §4). v_image [H, W, D], v_alpha [H, W];
// grads [kGradSlices, N, 6 + D] (any contents: zeroed here, one slice per group of
// tiles, then summed into slice 0, which holds the result), per Gaussian the sums over
// its pixels of
// (v_sigma dx, v_sigma dy, v_sigma dx^2, v_sigma dx dy, v_sigma dy^2, v_opacity,
// v_colors...). The caller turns them into v_mean2d = (a S0 + b S1, b S0 + c S1) and
// v_conic = (S2 / 2, S3, S4 / 2): linear, so it is done once per Gaussian, not per tile.
template <int DT>
int backward_tiles(const GParam* gp, const float* colors, const int d_, const float* bg,
                   const int32_t* tile_offsets, const int32_t* flatten_ids, int tw, int th,
                   int tile, int width, int height, const float* t_final,
                   const int32_t* last_in, const float* v_image, const float* v_alpha,
                   int64_t n, float* grads, int nt) {
  const int d = DT > 0 ? DT : d_;
  const int n_tiles = tw * th;
  const int s = 6 + d;
  int failed = 0;
#pragma omp parallel num_threads(nt) reduction(| : failed) \
    firstprivate(gp, colors, d, s, bg, tile_offsets, flatten_ids, tw, tile, width, height, \
                 t_final, last_in, v_image, v_alpha, n, grads)
  {
    const Tile t0 = make_tile(0, tw, tile, width, height);
    const int npix = t0.npix;
    float* tt = falloc(npix);
    float* bv = falloc(npix);   // <colour behind, v>
    float* sv = falloc(npix);   // T_final (v_alpha - <bg, v>)
    int32_t* last = reinterpret_cast<int32_t*>(falloc(npix));
    float* vloc = falloc((size_t)npix * std::max(d, 1));
    float* colx = falloc(t0.rs);
    const int s_pad = (s + L - 1) / L * L;
    vf* acc_heap = reinterpret_cast<vf*>(falloc((size_t)L * s_pad));
    vf acc_local[DT > 0 ? (6 + DT + L - 1) / L * L : 1];
    vf* acc = DT > 0 ? acc_local : acc_heap;
    if (!tt || !bv || !sv || !last || !vloc || !colx || !acc_heap) {
      failed = 1;
    } else {
      for (int j = 0; j < s_pad; ++j) acc[j] = splat(0.0f);  // padding stays zero
    }
    // The gradient sums are split into kGradSlices slices, not one per thread: slice
    // sl holds tiles sl, sl + kGradSlices, ... in tile order, and the slices are added
    // in slice order below. Which thread runs a slice does not matter, so gradients
    // are the same bits on every run and at every thread count (one slice per thread
    // made a run's answer depend on --threads, which training amplified). Each slice
    // is zeroed by the thread that fills it.
#pragma omp for schedule(dynamic, 1)
    for (int sl = 0; sl < kGradSlices; ++sl) {
      float* gbuf = grads + (int64_t)sl * n * s;
      std::memset(gbuf, 0, sizeof(float) * n * s);
      for (int ti = sl; ti < n_tiles; ti += kGradSlices) {
        if (failed) continue;  // no scratch memory: every thread still reaches the loop
        const Tile t = make_tile(ti, tw, tile, width, height);
        const int32_t start = tile_offsets[ti];
        int32_t max_last = -1;
        for (int ly = 0; ly < tile; ++ly)
          for (int lx = 0; lx < t.rs; ++lx) {
            const int p = ly * t.rs + lx;
            if (ly < t.rows && lx < t.cols) {
              const int64_t pg = (int64_t)(t.y0 + ly) * width + t.x0 + lx;
              const float tf = t_final[pg];
              const float* vp = v_image + pg * d;
              float bgdot = 0.0f;
              if (bg)
                for (int j = 0; j < d; ++j) bgdot += bg[j] * vp[j];
              for (int j = 0; j < d; ++j) vloc[(size_t)j * npix + p] = vp[j];
              tt[p] = tf;
              sv[p] = tf * (v_alpha[pg] - bgdot);
              last[p] = last_in[pg];
              max_last = std::max(max_last, last[p]);
            } else {
              for (int j = 0; j < d; ++j) vloc[(size_t)j * npix + p] = 0.0f;
              tt[p] = 1.0f;
              sv[p] = 0.0f;
              last[p] = -1;
            }
            bv[p] = 0.0f;
          }
        if (max_last < start) continue;
        for (int lx = 0; lx < t.rs; ++lx) colx[lx] = (float)(t.x0 + lx) + 0.5f;

        for (int32_t idx = max_last; idx >= start; --idx) {
          if (idx - kPrefetch >= start) {
            const int32_t ahead = flatten_ids[idx - kPrefetch];
            __builtin_prefetch(gp + ahead);
            const float* gr = gbuf + (int64_t)ahead * s;
            __builtin_prefetch(gr, 1);
            __builtin_prefetch(gr + s - 1, 1);
          }
          const int32_t gid = flatten_ids[idx];
          const GParam& g = gp[gid];
          if (!(g.thr >= 0.0f)) continue;
          int ly0, ly1, k0, k1;
          if (!box(g, t, ly0, ly1, k0, k1)) continue;
          const float* col = colors + (int64_t)gid * d;
          const vf vu = splat(g.u), vo = splat(g.o);
          const vi vidx = splati(idx);
          const vf z = splat(0.0f);
          // acc: sums over the tile's pixels of (v_sigma dx, v_sigma dy, v_sigma dx^2,
          // v_sigma dx dy, v_sigma dy^2, v_opacity, v_colors...), the layout of grads.
          for (int j = 0; j < s; ++j) acc[j] = z;
          bool touched = false;
          for (int ly = ly0; ly <= ly1; ++ly) {
            const Row r = row_of(g, t, ly);
            const vf vdy = splat(r.dy);
            for (int k = k0; k <= k1; ++k) {
              const int p = ly * t.rs + k * L;
              const vf dx = vu - ldf(colx + k * L);
              const vf sig = sigma_of(g, r, dx);
              // Only pairs the forward composited: idx <= last, same tests as there.
              const vi m0 = (vi)(vidx <= ldi(last + p)) & sigma_ok(g, sig);
              if (!mask_bits(m0)) continue;
              const vf e = vexp(-sig);
              const vf oe = vo * e;
              const vf al = vmin(oe, splat(kMaxAlpha));
              const vi m = m0 & (vi)(al >= splat(kAlphaThreshold));
              touched = true;
              // T recovery: T_i = T_{i+1} / max(1e-6, 1 - alpha_i).
              const vf ra = splat(1.0f) / vmax(splat(1.0f) - al, splat(kMinOneMinusAlpha));
              const vf tv = ldf(tt + p);
              const vf ti_ = tv * ra;
              stf(tt + p, sel(m, ti_, tv));
              const vf w = sel(m, al * ti_, z);
              vf cv = z;
              const float* vp = vloc + p;
              for (int j = 0; j < d; ++j, vp += npix) {
                const vf vd = ldf(vp);
                cv = vfma(splat(col[j]), vd, cv);
                acc[6 + j] = vfma(w, vd, acc[6 + j]);
              }
              const vf bvv = ldf(bv + p);
              // v_alpha = <c T_i - buf ra, v> + T_final ra (v_alpha_out - <bg, v>)
              const vf va = ti_ * cv - ra * bvv + ra * ldf(sv + p);
              stf(bv + p, vfma(w, cv, bvv));
              // Clamp active (o exp(-sigma) > 0.99): no gradient to sigma or opacity.
              const vi gm = m & ~(vi)(oe > splat(kMaxAlpha));
              const vf v_o = sel(gm, e * va, z);
              const vf v_sig = -(vo * v_o);
              const vf gdx = v_sig * dx, gdy = v_sig * vdy;
              acc[0] += gdx;
              acc[1] += gdy;
              acc[2] = vfma(gdx, dx, acc[2]);
              acc[3] = vfma(gdx, vdy, acc[3]);
              acc[4] = vfma(gdy, vdy, acc[4]);
              acc[5] += v_o;
            }
          }
          if (!touched) continue;
          // One transposed reduction per 8 sums, added straight into the buffer.
          float* gr = gbuf + (int64_t)gid * s;
          int j = 0;
          for (; j + L <= s; j += L) stf(gr + j, ldf(gr + j) + reduce8(acc + j));
          if (j < s) {
            const vf tail = reduce8(acc + j);  // acc is padded to a multiple of 8
            for (int l = 0; j + l < s; ++l) gr[j + l] += tail[l];
          }
        }
      }
    }
    // (implicit barrier) Sum the slices into slice 0, in slice order.
#pragma omp for schedule(static)
    for (int64_t i = 0; i < n * s; ++i) {
      float sum = grads[i];
      for (int k = 1; k < kGradSlices; ++k) sum += grads[(int64_t)k * n * s + i];
      grads[i] = sum;
    }
    free(tt);
    free(bv);
    free(sv);
    free(last);
    free(vloc);
    free(colx);
    free(acc_heap);
  }
  return failed ? 2 : 0;
}


// Row chunks of about equal nnz, so a dynamic schedule balances empty and busy rows.
void nnz_chunks(const int32_t* indptr, int64_t rows, int nchunks, int64_t* bounds) {
  const int64_t nnz = indptr[rows];
  bounds[0] = 0;
  for (int c = 1; c < nchunks; ++c) {
    const int64_t target = nnz * c / nchunks;
    bounds[c] = std::max<int64_t>(
        bounds[c - 1], std::lower_bound(indptr, indptr + rows, (int32_t)target) - indptr);
  }
  bounds[nchunks] = rows;
}

// out[r, c0:c0+w] = sum_k values[k] f[indices[k], c0:c0+w] for 8 (NB - 1) < w <= 8 NB.
// The last block is a masked 4-lane vector when at most 4 columns remain (D = 12: one
// 8-lane and one 4-lane FMA per nonzero), else a masked 8-lane one.
template <int NB>
void spmm_block(const int32_t* indptr, const int32_t* indices, const float* values,
                const float* f, int64_t r0, int64_t r1, int d, int c0, int w, float* out) {
#if PTOVS_AVX2
  const int tail = w - (NB - 1) * L;  // 1..8 columns in the last block
  const bool half = tail <= 4;
  const __m256i mask8 = _mm256_cmpgt_epi32(_mm256_set1_epi32(tail),
                                           _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
  const __m128i mask4 = _mm256_castsi256_si128(mask8);
  // Two accumulator sets: two independent FMA chains per block (measured 20 % faster
  // than one; more sets gain nothing).
  constexpr int U = 2;
  for (int64_t r = r0; r < r1; ++r) {
    __m256 acc[U][NB];
    __m128 acc4[U];
    for (int u = 0; u < U; ++u) {
      for (int b = 0; b < NB; ++b) acc[u][b] = _mm256_setzero_ps();
      acc4[u] = _mm_setzero_ps();
    }
    auto step = [&](int u, int32_t k) {
      const __m256 val = _mm256_set1_ps(values[k]);
      const float* fr = f + (int64_t)indices[k] * d + c0;
      for (int b = 0; b < NB - 1; ++b)
        acc[u][b] = _mm256_fmadd_ps(val, _mm256_loadu_ps(fr + b * L), acc[u][b]);
      if (half)
        acc4[u] = _mm_fmadd_ps(_mm256_castps256_ps128(val),
                               _mm_maskload_ps(fr + (NB - 1) * L, mask4), acc4[u]);
      else
        acc[u][NB - 1] = _mm256_fmadd_ps(
            val, _mm256_maskload_ps(fr + (NB - 1) * L, mask8), acc[u][NB - 1]);
    };
    const int32_t k1 = indptr[r + 1];
    int32_t k = indptr[r];
    for (; k + U <= k1; k += U)
      for (int u = 0; u < U; ++u) step(u, k + u);
    for (; k < k1; ++k) step(0, k);
    float* o = out + r * d + c0;
    for (int b = 0; b < NB - 1; ++b)
      _mm256_storeu_ps(o + b * L, _mm256_add_ps(acc[0][b], acc[1][b]));
    if (half)
      _mm_maskstore_ps(o + (NB - 1) * L, mask4, _mm_add_ps(acc4[0], acc4[1]));
    else
      _mm256_maskstore_ps(o + (NB - 1) * L, mask8,
                          _mm256_add_ps(acc[0][NB - 1], acc[1][NB - 1]));
  }
#else
  float acc[NB * L];
  for (int64_t r = r0; r < r1; ++r) {
    for (int j = 0; j < w; ++j) acc[j] = 0.0f;
    for (int32_t k = indptr[r]; k < indptr[r + 1]; ++k) {
      const float val = values[k];
      const float* fr = f + (int64_t)indices[k] * d + c0;
      for (int j = 0; j < w; ++j) acc[j] += val * fr[j];
    }
    float* o = out + r * d + c0;
    for (int j = 0; j < w; ++j) o[j] = acc[j];
  }
#endif
}

void spmm_rows(const int32_t* indptr, const int32_t* indices, const float* values,
               const float* f, int64_t r0, int64_t r1, int d, float* out) {
  for (int c0 = 0; c0 < d; c0 += 4 * L) {
    const int w = std::min(4 * L, d - c0);
    switch ((w + L - 1) / L) {
      case 1: spmm_block<1>(indptr, indices, values, f, r0, r1, d, c0, w, out); break;
      case 2: spmm_block<2>(indptr, indices, values, f, r0, r1, d, c0, w, out); break;
      case 3: spmm_block<3>(indptr, indices, values, f, r0, r1, d, c0, w, out); break;
      default: spmm_block<4>(indptr, indices, values, f, r0, r1, d, c0, w, out); break;
    }
  }
}

#define PTOVS_DISPATCH_D(fn, d, ...)               \
  switch (d) {                                     \
    case 1: return fn<1>(__VA_ARGS__);             \
    case 2: return fn<2>(__VA_ARGS__);             \
    case 3: return fn<3>(__VA_ARGS__);             \
    case 4: return fn<4>(__VA_ARGS__);             \
    case 8: return fn<8>(__VA_ARGS__);             \
    case 12: return fn<12>(__VA_ARGS__);           \
    case 16: return fn<16>(__VA_ARGS__);           \
    default: return fn<0>(__VA_ARGS__);            \
  }

template <typename... A>
int forward_any(int d, A... args) {
  PTOVS_DISPATCH_D(forward_tiles, d, args...)
}
template <typename... A>
int backward_any(int d, A... args) {
  PTOVS_DISPATCH_D(backward_tiles, d, args...)
}

}  // namespace

extern "C" {

int ptovs_abi_version() { return 3; }

// The leading dimension of ptovs_composite_bwd's grads.
int ptovs_grad_slices() { return kGradSlices; }

int ptovs_simd_width() { return PTOVS_AVX2 ? 8 : 0; }

// Forward compositing. Outputs: image [H, W, D], alpha [H, W], t_final [H, W],
// n_contrib [H, W] (composited count), last [H, W] (flatten_ids position of the last
// composited Gaussian, -1 if none). bg may be null.
int ptovs_composite_fwd(const float* means2d, const float* conics, const float* opac,
                        const float* colors, const float* bg, int64_t n, int d,
                        const int32_t* tile_offsets, const int32_t* flatten_ids, int tw,
                        int th, int tile, int width, int height, float* image,
                        float* alpha, float* t_final, int32_t* n_contrib, int32_t* last,
                        int nt) {
  GParam* gp = alloc_params(n);
  if (!gp) return 2;
  precompute(means2d, conics, opac, n, gp, nt);
  const int rc = forward_any(d, gp, colors, d, bg, tile_offsets, flatten_ids, tw, th, tile,
                               width, height, image, alpha, t_final, n_contrib, last,
                               nullptr, nullptr, nullptr, nt);
  free(gp);
  return rc;
}

// Blend weights in CSR row order. Pass 1 (rowptr null): writes n_contrib [H, W].
// Pass 2: rowptr [H*W + 1] (exclusive prefix sum of pass 1), writes ids and weights.
int ptovs_blend_weights(const float* means2d, const float* conics, const float* opac,
                        int64_t n, const int32_t* tile_offsets, const int32_t* flatten_ids,
                        int tw, int th, int tile, int width, int height, int32_t* n_contrib,
                        const int64_t* rowptr, int32_t* out_ids, float* out_w, int nt) {
  GParam* gp = alloc_params(n);
  if (!gp) return 2;
  precompute(means2d, conics, opac, n, gp, nt);
  const int rc = forward_tiles<0>(gp, nullptr, 0, nullptr, tile_offsets, flatten_ids, tw, th,
                               tile, width, height, nullptr, nullptr, nullptr,
                               rowptr ? nullptr : n_contrib, nullptr, rowptr,
                               rowptr ? out_ids : nullptr, out_w, nt);
  free(gp);
  return rc;
}


// Backward: grads [nt, N, 6 + D] scratch (any contents); the result is left in slice 0,
// layout as for backward_tiles.
int ptovs_composite_bwd(const float* means2d, const float* conics, const float* opac,
                        const float* colors, const float* bg, int64_t n, int d,
                        const int32_t* tile_offsets, const int32_t* flatten_ids, int tw,
                        int th, int tile, int width, int height, const float* t_final,
                        const int32_t* last, const float* v_image, const float* v_alpha,
                        float* grads, int nt) {
  GParam* gp = alloc_params(n);
  if (!gp) return 2;
  precompute(means2d, conics, opac, n, gp, nt);
  const int rc = backward_any(d, gp, colors, d, bg, tile_offsets, flatten_ids, tw, th, tile,
                                width, height, t_final, last, v_image, v_alpha, n, grads, nt);
  free(gp);
  return rc;
}


// CSR [rows, cols] @ f [cols, D] -> out [rows, D] (int32 indptr and indices).
int ptovs_spmm(const int32_t* indptr, const int32_t* indices, const float* values,
               int64_t rows, const float* f, int d, float* out, int nt) {
  if (rows <= 0 || d <= 0) return 0;
  const int nchunks = std::max<int64_t>(1, std::min<int64_t>(rows, (int64_t)nt * 32));
  int64_t* bounds = static_cast<int64_t*>(std::malloc(sizeof(int64_t) * (nchunks + 1)));
  if (!bounds) return 2;
  nnz_chunks(indptr, rows, nchunks, bounds);
#pragma omp parallel for num_threads(nt) schedule(dynamic, 1)
  for (int c = 0; c < nchunks; ++c)
    spmm_rows(indptr, indices, values, f, bounds[c], bounds[c + 1], d, out);
  std::free(bounds);
  return 0;
}

// Transpose CSR [rows, cols] -> CSR [cols, rows]; each output row lists its entries in
// ascending input row. Scratch counts [nt, cols] int32 (any contents).
int ptovs_csr_transpose(const int32_t* indptr, const int32_t* indices, const float* values,
                        int64_t rows, int64_t cols, int32_t* t_indptr, int32_t* t_indices,
                        float* t_values, int32_t* counts, int nt) {
  if (nt < 1) nt = 1;
  int64_t* bounds = static_cast<int64_t*>(std::malloc(sizeof(int64_t) * (nt + 1)));
  if (!bounds) return 2;
  nnz_chunks(indptr, rows, nt, bounds);
  // Each thread owns a contiguous range of input rows, so its entries land after those
  // of lower threads in every output row and each output row stays sorted.
#pragma omp parallel num_threads(nt)
  {
#ifdef _OPENMP
    const int nthreads = omp_get_num_threads();
#else
    const int nthreads = 1;
#endif
    for (int tid = thread_id(); tid < nt; tid += nthreads) {
      int32_t* cnt = counts + (int64_t)tid * cols;
      std::fill(cnt, cnt + cols, 0);
      for (int32_t k = indptr[bounds[tid]]; k < indptr[bounds[tid + 1]]; ++k) ++cnt[indices[k]];
    }
#pragma omp barrier
#pragma omp single
    {
      int32_t run = 0;
      for (int64_t c = 0; c < cols; ++c) {
        t_indptr[c] = run;
        for (int tid = 0; tid < nt; ++tid) {
          int32_t* cnt = counts + (int64_t)tid * cols + c;
          const int32_t v = *cnt;
          *cnt = run;  // becomes this thread's write cursor for output row c
          run += v;
        }
      }
      t_indptr[cols] = run;
    }
    for (int tid = thread_id(); tid < nt; tid += nthreads) {
      int32_t* cur = counts + (int64_t)tid * cols;
      for (int64_t r = bounds[tid]; r < bounds[tid + 1]; ++r)
        for (int32_t k = indptr[r]; k < indptr[r + 1]; ++k) {
          const int32_t pos = cur[indices[k]]++;
          t_indices[pos] = (int32_t)r;
          t_values[pos] = values[k];
        }
    }
  }
  std::free(bounds);
  return 0;
}

}  // extern "C"
