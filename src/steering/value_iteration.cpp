// Value iteration on P_s (dissertation 5.4.3), Gauss-Seidel with alternating sweep orders.
#include "needle_guidance/steering/value_iteration.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <numeric>
#include <set>
#include <stdexcept>
#include <string>
#include <thread>

#ifdef __linux__
#include <sys/mman.h>
#endif

namespace needle_guidance::steering {
namespace {

/// Number of distinct sweep orders (x descending/ascending x y descending/ascending).
constexpr int kSweepOrders = 4;

struct Band {
  int row_begin = 0;
  int row_end = 0;
  int index = 0;  // the thread's number
};

/// Shared read-only context of one solve.
struct Context {
  const SteeringModel* model = nullptr;
  const GridSpec* grid = nullptr;
  const std::uint8_t* cells = nullptr;
  float* values = nullptr;
  const float* snapshot = nullptr;  // rows of neighbouring bands, copied at the start of a sweep
  std::uint8_t* controls = nullptr;
  const StencilEntry* const* stencil_begin = nullptr;  // per (b * nc + k) * 2 + u, plus end
  const StencilEntry* const* stencil_end = nullptr;
  bool split = false;  // kInterpolated: positions off the fast path use expectedSplit
  const struct ArcTables* arcs = nullptr;   // kInterpolated: per-arc corners, per-slot deflections
  struct ChangeTracker* changes = nullptr;  // null: every free position is updated every sweep
  /// Per position: its values changed since they were last copied to the snapshot (the band
  /// that owns the position sets it; the snapshot is taken between sweeps).
  std::uint8_t* unsaved = nullptr;
};

/// Skips positions whose update could not move their values by `skip_below` or more. The
/// Bellman update (eq. 5.2) is a maximum of weighted means with weights summing to <= 1, so a
/// position's new values differ from its old ones by at most the largest change of any successor
/// since its last update. The changes are kept per block of kBlock x kBlock positions (the
/// largest of its positions), and a position reads the blocks that hold any of its successors,
/// a superset of them, so the bound stays a bound at a fraction of the reads. `pending`
/// accumulates it (changes in the previous sweep plus those already made in this one, counted
/// twice at worst); a position is updated once its bound reaches skip_below. Each thread records
/// its own changes of the current sweep; those of another thread's band are counted one sweep
/// later (in `previous`), as their values are too (the snapshot), so the result does not depend
/// on timing.
struct ChangeTracker {
  static constexpr int kBlock = 4;  // positions per block side
  /// Blocks of one column offset with consecutive rows dby_lo .. dby_hi (contiguous in memory).
  struct Run {
    std::int16_t dbx = 0, dby_lo = 0, dby_hi = 0;
  };
  float skip_below = 0.0f;
  int nbx = 0, nby = 0;                     // blocks along x and y
  std::vector<float> previous;              // per block: max |change| in the previous sweep
  std::vector<std::vector<float>> current;  // per thread, per block: max |change| this sweep
  std::vector<float> pending;  // per position: bound on its change since its last update
  std::vector<Run> runs;

  std::size_t block(int ix, int iy) const {
    return static_cast<std::size_t>((ix / kBlock) * nby + iy / kBlock);
  }
  /// Adds this sweep's bound for position (ix, iy) and says whether it must be updated.
  bool due(std::int64_t pos, int ix, int iy, int thread) {
    const int bx = ix / kBlock, by = iy / kBlock;
    const float* cur = current[static_cast<std::size_t>(thread)].data();
    float bound = 0.0f;
    for (const Run& r : runs) {
      const int x = bx + r.dbx;
      if (x < 0 || x >= nbx) {
        continue;
      }
      const int lo = std::max(0, by + r.dby_lo), hi = std::min(nby - 1, by + r.dby_hi);
      const std::size_t column = static_cast<std::size_t>(x) * static_cast<std::size_t>(nby);
      for (int y = lo; y <= hi; ++y) {
        bound = std::max(bound, previous[column + y] + cur[column + y]);
      }
    }
    float& p = pending[static_cast<std::size_t>(pos)];
    p += bound;
    return p >= skip_below;
  }
  void record(int ix, int iy, int thread, float change) {
    float& c = current[static_cast<std::size_t>(thread)][block(ix, iy)];
    c = std::max(c, change);
  }
  /// This sweep's changes become the previous ones.
  void endSweep() {
    std::fill(previous.begin(), previous.end(), 0.0f);
    for (std::vector<float>& cur : current) {
      for (std::size_t i = 0; i < cur.size(); ++i) {
        previous[i] = std::max(previous[i], cur[i]);
      }
      std::fill(cur.begin(), cur.end(), 0.0f);
    }
  }
};

/// kInterpolated, factored: the value after tracing arc a (bevel * nc + orientation) from a
/// position depends on the arc only, so it is computed once per arc (four corners) and each
/// control then sums P(d) over the arcs of its deflections, instead of 4 corners per deflection.
struct ArcTables {
  std::vector<std::int64_t> offset;  // per arc * 4 + corner: next state minus the position's base
  std::vector<float> weight;         // bilinear weight of the corner
  std::vector<std::int16_t> dy;      // row displacement of the corner
  std::vector<std::uint8_t> corner;  // corner id (bit of endMask)
  /// Per control u: P(d) for d = first[u] .. first[u] + p[u].size() - 1 (orientation steps).
  std::vector<float> p[2];
  int first[2] = {0, 0};
  int first_min = 0;  // min(first[0], first[1])
  int ext_len = 0;    // nc + the widest deflection span: length of one bevel's wrapped values
  std::vector<std::uint16_t> ext_src;  // per j < ext_len: orientation (j + first_min) mod nc
  /// Per phase (position index mod phase count): one offset per distinct cache line the corners
  /// and the values of a position lie on, for the value table's alignment (set by prefetchLines).
  std::vector<std::vector<std::int64_t>> lines;
};

/// ArcTables::lines for a value table at `values`: the corners of a position and its own values
/// lie on these cache lines, requested together before the corners are read so that their memory
/// latencies overlap. A position's values start at one of few places within a line (2 nc floats per
/// position), one list per place.
void prefetchLines(ArcTables& t, const float* values, int nc) {
  constexpr std::int64_t kLineFloats = 64 / sizeof(float);
  const std::int64_t per_position = 2 * nc;
  const std::int64_t phases = kLineFloats / std::gcd(per_position, kLineFloats);
  const auto start = static_cast<std::int64_t>(
      (reinterpret_cast<std::uintptr_t>(values) / sizeof(float)) % kLineFloats);
  t.lines.assign(static_cast<std::size_t>(phases), {});
  for (std::int64_t ph = 0; ph < phases; ++ph) {
    const std::int64_t phase = (start + ph * per_position) % kLineFloats;
    std::vector<std::pair<std::int64_t, std::int64_t>> by_line;  // (line, offset)
    std::vector<std::int64_t> offsets = t.offset;
    for (std::int64_t own = 0; own < per_position; ++own) {
      offsets.push_back(own);  // the position's own values, read for their change
    }
    for (const std::int64_t off : offsets) {
      const std::int64_t f = phase + off;
      by_line.push_back({f >= 0 ? f / kLineFloats : -((-f + kLineFloats - 1) / kLineFloats), off});
    }
    std::sort(by_line.begin(), by_line.end());
    std::vector<std::int64_t>& lines = t.lines[static_cast<std::size_t>(ph)];
    for (std::size_t i = 0; i < by_line.size(); ++i) {
      if (i == 0 || by_line[i].first != by_line[i - 1].first) {
        lines.push_back(by_line[i].second);
      }
    }
  }
}

/// Expected P_s of one control: sum_j p_ij P_s(x_j) over the stencil (eq. 5.2). kCheck: some
/// arcs from this position fail; kBand: successors outside rows [row_begin, row_end) are read
/// from the snapshot (they belong to another thread).
template <bool kCheck, bool kBand>
inline float expected(const Context& c, const StencilEntry* begin, const StencilEntry* end,
                      std::int64_t s, const std::uint64_t* mask, int iy, const Band& band) {
  float sum = 0.0f;
  for (const StencilEntry* e = begin; e != end; ++e) {
    if (kCheck && !((mask[e->arc >> 6] >> (e->arc & 63)) & 1u)) {
      continue;  // the arc fails: P_s = 0
    }
    const std::int64_t j = s + e->offset;
    float v;
    if (kBand) {
      const int row = iy + e->dy;
      v = row >= band.row_begin && row < band.row_end ? c.values[j] : c.snapshot[j];
    } else {
      v = c.values[j];
    }
    sum += e->probability * v;
  }
  return sum;
}

template <bool kCheck, bool kBand>
float updatePosition(const Context& c, std::int64_t pos, int iy, const Band& band) {
  const int nc = c.grid->nc;
  const std::uint64_t* mask = c.model->validityMask(pos);
  float max_change = 0.0f;
  const std::int64_t base = pos * 2 * nc;
  for (int bk = 0; bk < 2 * nc; ++bk) {
    const std::int64_t s = base + bk;
    const float q_insert = expected<kCheck, kBand>(c, c.stencil_begin[2 * bk],
                                                   c.stencil_end[2 * bk], s, mask, iy, band);
    const float q_flip = expected<kCheck, kBand>(c, c.stencil_begin[2 * bk + 1],
                                                 c.stencil_end[2 * bk + 1], s, mask, iy, band);
    const bool flip = q_flip > q_insert;  // ties keep insert
    const float best = flip ? q_flip : q_insert;
    max_change = std::max(max_change, std::abs(best - c.values[s]));
    c.values[s] = best;
    c.controls[s] = flip ? 1 : 0;
  }
  return max_change;
}

/// Eight floats: one AVX register in the AVX2 build, two SSE registers in the plain one. Plain
/// multiplies and adds, element by element, so either build gives the same sums.
using Floats8 = float __attribute__((vector_size(32)));
constexpr int kLanes = 8;

/// q[k] = sum_i p[i] e[k + i] for k < kBlocks * kLanes, summed over ascending i from 0 as the
/// plain loop does, but held in registers across i instead of read and written per term.
template <int kBlocks>
inline void convolveBlocks(const float* p, int np, const float* e, float* q) {
  Floats8 acc[kBlocks];
  for (int j = 0; j < kBlocks; ++j) {
    acc[j] = Floats8{};
  }
  for (int i = 0; i < np; ++i) {
    const Floats8 pi = Floats8{} + p[i];
    for (int j = 0; j < kBlocks; ++j) {
      Floats8 ej;
      std::memcpy(&ej, e + i + j * kLanes, sizeof(ej));
      acc[j] += pi * ej;
    }
  }
  std::memcpy(q, acc, sizeof(acc));
}

/// The deflection sums of one position from the values after each arc (`after`: 2 nc, then
/// scratch), the better control of every state written to `values` and `controls`; returns the
/// largest |change|. The sums are circular convolutions over the orientation: for bevel b and
/// control u, q_u(k) = sum_i P_u(i) after(traced, k + first_u + i). Each bevel's values are
/// unrolled once (wrapped around) so the inner loop runs over contiguous k, 32 (then 8) of them
/// at a time held in registers. Built for AVX2 and plain x86-64, chosen at load time: each
/// element is the same sum in the same order either way (no fused multiply-add), so the table
/// does not depend on the processor.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
__attribute__((target_clones("avx2", "default")))
#endif
float deflectionSums(const ArcTables& t, int nc, float* after, float* values,
                     std::uint8_t* controls) {
  float* ext = after + 2 * nc;
  for (int tr = 0; tr < 2; ++tr) {
    float* e = ext + tr * t.ext_len;
    const float* src = after + tr * nc;
    for (int j = 0; j < t.ext_len; ++j) {
      e[j] = src[t.ext_src[static_cast<std::size_t>(j)]];
    }
  }
  float* q = ext + 2 * t.ext_len;  // q[(b * 2 + u) * nc + k]
  for (int b = 0; b < 2; ++b) {
    for (int u = 0; u < 2; ++u) {
      const int traced = u == 0 ? b : 1 - b;
      const float* e = ext + traced * t.ext_len + (t.first[u] - t.first_min);
      float* qu = q + (b * 2 + u) * nc;
      const float* p = t.p[u].data();
      const int np = static_cast<int>(t.p[u].size());
      int k = 0;
      for (; k + 4 * kLanes <= nc; k += 4 * kLanes) {
        convolveBlocks<4>(p, np, e + k, qu + k);
      }
      for (; k + kLanes <= nc; k += kLanes) {
        convolveBlocks<1>(p, np, e + k, qu + k);
      }
      for (; k < nc; ++k) {
        float sum = 0.0f;
        for (int i = 0; i < np; ++i) {
          sum += p[i] * e[k + i];
        }
        qu[k] = sum;
      }
    }
  }
  float max_change = 0.0f;
  Floats8 max8{};  // the largest |change| per lane (a maximum: exact in any order)
  for (int b = 0; b < 2; ++b) {
    const float* q_insert = q + (b * 2) * nc;
    const float* q_flip = q + (b * 2 + 1) * nc;
    float* v = values + b * nc;
    std::uint8_t* ctl = controls + b * nc;
    int k = 0;
    for (; k + kLanes <= nc; k += kLanes) {
      Floats8 qi, qf, old;
      std::memcpy(&qi, q_insert + k, sizeof(qi));
      std::memcpy(&qf, q_flip + k, sizeof(qf));
      std::memcpy(&old, v + k, sizeof(old));
      const auto flip = qf > qi;  // ties keep insert
      const Floats8 best = flip ? qf : qi;
      const Floats8 diff = best - old;
      const Floats8 change = diff > Floats8{} ? diff : -diff;
      max8 = change > max8 ? change : max8;
      std::memcpy(v + k, &best, sizeof(best));
      for (int j = 0; j < kLanes; ++j) {
        ctl[k + j] = flip[j] ? 1 : 0;
      }
    }
    for (; k < nc; ++k) {
      const bool flip = q_flip[k] > q_insert[k];  // ties keep insert
      const float best = flip ? q_flip[k] : q_insert[k];
      max_change = std::max(max_change, std::abs(best - v[k]));
      v[k] = best;
      ctl[k] = flip ? 1 : 0;
    }
  }
  for (int j = 0; j < kLanes; ++j) {
    max_change = std::max(max_change, max8[j]);
  }
  return max_change;
}

/// kPlain: every arc from the position is valid and keeps its four corners (allArcsValid).
template <bool kBand, bool kPlain>
float updateFactoredPosition(const Context& c, std::int64_t pos, int iy, const Band& band,
                             std::vector<float>& after) {
  const int nc = c.grid->nc;
  const ArcTables& t = *c.arcs;
  const std::uint64_t* mask = c.model->validityMask(pos);
  const std::int64_t base = pos * 2 * nc;
  {
    // Addresses, not pointers: a failing arc's corners may lie off the table, and a prefetch
    // never faults.
    const auto table = reinterpret_cast<std::uintptr_t>(c.values + base);
    const auto phase = static_cast<std::size_t>(pos % static_cast<std::int64_t>(t.lines.size()));
    for (const std::int64_t off : t.lines[phase]) {
      __builtin_prefetch(reinterpret_cast<const void*>(table + off * sizeof(float)));
    }
  }
  for (int a = 0; a < 2 * nc; ++a) {
    if (!kPlain && !((mask[a >> 6] >> (a & 63)) & 1u)) {
      after[static_cast<std::size_t>(a)] = 0.0f;  // the arc fails
      continue;
    }
    const std::uint8_t em = kPlain ? 15 : c.model->endMask(pos, a);
    if (!kPlain && (em & SteeringModel::kEndInTarget)) {
      after[static_cast<std::size_t>(a)] = 1.0f;
      continue;
    }
    float kept = 0.0f, weighted = 0.0f;
    for (int i = 0; i < 4; ++i) {
      const auto ai = static_cast<std::size_t>(a * 4 + i);
      if (!kPlain && !((em >> t.corner[ai]) & 1u)) {
        continue;
      }
      const std::int64_t j = base + t.offset[ai];
      float v;
      if (kBand) {
        const int row = iy + t.dy[ai];
        v = row >= band.row_begin && row < band.row_end ? c.values[j] : c.snapshot[j];
      } else {
        v = c.values[j];
      }
      kept += t.weight[ai];
      weighted += t.weight[ai] * v;
    }
    after[static_cast<std::size_t>(a)] = kept > 0.0f ? weighted / kept : 0.0f;
  }
  return deflectionSums(t, nc, after.data(), c.values + base, c.controls + base);
}

/// The per-arc corners and per-slot deflections of a kInterpolated model's stencils.
ArcTables arcTables(const SteeringModel& model) {
  const int nc = model.grid().nc;
  ArcTables t;
  t.offset.assign(static_cast<std::size_t>(8 * nc), 0);
  t.weight.assign(static_cast<std::size_t>(8 * nc), 0.0f);
  t.dy.assign(static_cast<std::size_t>(8 * nc), 0);
  t.corner.assign(static_cast<std::size_t>(8 * nc), 0);
  int span = 0;
  for (int u = 0; u < 2; ++u) {
    const std::vector<double>& probs = model.deflectionProbabilities(static_cast<Control>(u));
    t.first[u] = model.firstDeflection(static_cast<Control>(u));
    t.p[u].assign(probs.begin(), probs.end());  // the same P(d) in every slot of a control
    span = std::max(span, static_cast<int>(probs.size()));
  }
  t.first_min = std::min(t.first[0], t.first[1]);
  t.ext_len = nc + span + std::abs(t.first[0] - t.first[1]);
  for (int j = 0; j < t.ext_len; ++j) {
    t.ext_src.push_back(static_cast<std::uint16_t>(((j + t.first_min) % nc + nc) % nc));
  }
  for (int b = 0; b < 2; ++b) {
    for (int k = 0; k < nc; ++k) {
      for (int u = 0; u < 2; ++u) {
        const StencilEntry* begin =
            model.stencilBegin(k, static_cast<Bevel>(b), static_cast<Control>(u));
        const StencilEntry* end =
            model.stencilEnd(k, static_cast<Bevel>(b), static_cast<Control>(u));
        for (const StencilEntry* e = begin; e != end; e += 4) {
          const float p = e[0].probability + e[1].probability + e[2].probability + e[3].probability;
          for (int i = 0; i < 4; ++i) {
            const auto ai = static_cast<std::size_t>(e->arc * 4 + i);
            t.offset[ai] = e[i].offset + (b * nc + k);
            t.weight[ai] = p > 0.0f ? e[i].probability / p : 0.25f;
            t.dy[ai] = e[i].dy;
            t.corner[ai] = e[i].corner;
          }
        }
      }
    }
  }
  return t;
}

/// A tracker seeded with the only values that differ from 0 before the first sweep: the target
/// cells (P_s = 1, counted as a change of 1) and the arcs that end in the target. A position is
/// due in the first sweep only once a successor's value has risen from 0, so the first sweep
/// follows the front spreading back from the target instead of recomputing zeros: with every
/// successor at 0, eq. 5.2 gives 0 and the control insert (ties keep insert), which the
/// position already holds. The blocks read come from the model's stencils.
ChangeTracker changeTracker(const SteeringModel& model, float skip_below, int threads) {
  const GridSpec& g = model.grid();
  constexpr int kB = ChangeTracker::kBlock;
  ChangeTracker t;
  t.skip_below = skip_below;
  t.nbx = (g.nx + kB - 1) / kB;
  t.nby = (g.ny + kB - 1) / kB;
  const auto blocks = static_cast<std::size_t>(t.nbx) * static_cast<std::size_t>(t.nby);
  t.previous.assign(blocks, 0.0f);
  t.current.assign(static_cast<std::size_t>(threads), std::vector<float>(blocks, 0.0f));
  t.pending.assign(static_cast<std::size_t>(g.numPositions()), 0.0f);
  const bool interpolated = model.transitionModel() == TransitionModel::kInterpolated;
  for (int ix = 0; ix < g.nx; ++ix) {
    for (int iy = 0; iy < g.ny; ++iy) {
      const std::int64_t pos = g.position(ix, iy);
      if (model.cell(pos) == Cell::kTarget) {
        t.previous[t.block(ix, iy)] = 1.0f;
      } else if (interpolated && model.cell(pos) == Cell::kFree && !model.allArcsValid(pos)) {
        for (int a = 0; a < 2 * g.nc; ++a) {
          if (model.arcValid(pos, a) && (model.endMask(pos, a) & SteeringModel::kEndInTarget)) {
            t.pending[static_cast<std::size_t>(pos)] = std::numeric_limits<float>::infinity();
            break;
          }
        }
      }
    }
  }
  std::set<std::pair<int, int>> seen;  // distinct successors: (column offset, row offset)
  for (int b = 0; b < 2; ++b) {
    for (int k = 0; k < g.nc; ++k) {
      for (int u = 0; u < 2; ++u) {
        const auto bevel = static_cast<Bevel>(b);
        const auto control = static_cast<Control>(u);
        for (const StencilEntry* e = model.stencilBegin(k, bevel, control);
             e != model.stencilEnd(k, bevel, control); ++e) {
          seen.insert({(e->dpos - e->dy) / g.ny, e->dy});
        }
      }
    }
  }
  // Every block offset a successor of any position of a block falls in.
  const auto floorDiv = [](int a) { return a >= 0 ? a / kB : -((-a + kB - 1) / kB); };
  std::set<std::pair<int, int>> block_offsets;
  for (const auto& [dx, dy] : seen) {
    for (int o = 0; o < kB; ++o) {
      for (int p = 0; p < kB; ++p) {
        block_offsets.insert({floorDiv(o + dx), floorDiv(p + dy)});
      }
    }
  }
  for (const auto& [dbx, dby] : block_offsets) {  // by column, then row: merge consecutive rows
    if (!t.runs.empty() && t.runs.back().dbx == dbx && t.runs.back().dby_hi + 1 == dby) {
      t.runs.back().dby_hi = static_cast<std::int16_t>(dby);
    } else {
      t.runs.push_back({static_cast<std::int16_t>(dbx), static_cast<std::int16_t>(dby),
                        static_cast<std::int16_t>(dby)});
    }
  }
  return t;
}

/// One sweep of the rows in `band` (all columns), in the given order; returns max |change|.
float sweepBand(const Context& c, const Band& band, bool x_descending, bool y_descending, int reach,
                bool use_snapshot, std::int64_t& updated) {
  updated = 0;
  const GridSpec& g = *c.grid;
  float max_change = 0.0f;
  // kInterpolated scratch: after (2 nc), the two wrapped bevels (2 ext_len), q (4 nc).
  std::vector<float> after(c.split ? static_cast<std::size_t>(6 * g.nc + 2 * c.arcs->ext_len) : 0);
  for (int i = 0; i < g.nx; ++i) {
    const int ix = x_descending ? g.nx - 1 - i : i;
    const int rows = band.row_end - band.row_begin;
    for (int r = 0; r < rows; ++r) {
      const int iy = y_descending ? band.row_end - 1 - r : band.row_begin + r;
      const std::int64_t pos = g.position(ix, iy);
      if (c.cells[pos] != static_cast<std::uint8_t>(Cell::kFree)) {
        continue;  // absorbing (5.4.2)
      }
      if (c.changes != nullptr && !c.changes->due(pos, ix, iy, band.index)) {
        max_change = std::max(max_change, c.changes->pending[static_cast<std::size_t>(pos)]);
        continue;  // its values would move by less than skip_below
      }
      ++updated;
      const bool check = !c.model->allArcsValid(pos);
      // Only rows within reach of another thread's band read the snapshot; the workspace's own
      // lower and upper edges have no neighbour.
      const bool near_edge =
          use_snapshot && ((band.row_begin > 0 && iy - band.row_begin < reach) ||
                           (band.row_end < g.ny && band.row_end - 1 - iy < reach));
      float change;
      if (c.split) {
        if (near_edge) {
          change = check ? updateFactoredPosition<true, false>(c, pos, iy, band, after)
                         : updateFactoredPosition<true, true>(c, pos, iy, band, after);
        } else {
          change = check ? updateFactoredPosition<false, false>(c, pos, iy, band, after)
                         : updateFactoredPosition<false, true>(c, pos, iy, band, after);
        }
      } else if (near_edge) {
        change = check ? updatePosition<true, true>(c, pos, iy, band)
                       : updatePosition<false, true>(c, pos, iy, band);
      } else {
        change = check ? updatePosition<true, false>(c, pos, iy, band)
                       : updatePosition<false, false>(c, pos, iy, band);
      }
      if (c.unsaved != nullptr) {
        c.unsaved[pos] = 1;
      }
      if (c.changes != nullptr) {
        c.changes->record(ix, iy, band.index, change);
        c.changes->pending[static_cast<std::size_t>(pos)] = 0.0f;
      }
      max_change = std::max(max_change, change);
    }
  }
  return max_change;
}

/// Copies the rows within `reach` of a band boundary to the snapshot, so that neighbouring bands
/// read them race-free: only the positions whose values changed since their last copy (the
/// others already hold the same values there).
void copyBoundaryRows(const GridSpec& g, const std::vector<Band>& bands, int reach,
                      const float* values, float* snapshot, std::uint8_t* unsaved) {
  const std::size_t per_position = static_cast<std::size_t>(2 * g.nc);
  for (int ix = 0; ix < g.nx; ++ix) {
    for (std::size_t t = 1; t < bands.size(); ++t) {
      const int lo = std::max(0, bands[t].row_begin - reach);
      const int hi = std::min(g.ny, bands[t].row_begin + reach);
      for (int iy = lo; iy < hi; ++iy) {
        const std::int64_t pos = g.position(ix, iy);
        if (unsaved[pos] != 0) {
          const std::size_t first = static_cast<std::size_t>(pos) * per_position;
          std::memcpy(snapshot + first, values + first, per_position * sizeof(float));
          unsaved[pos] = 0;
        }
      }
    }
  }
}

/// `v` resized to n zeros. A table of many states is hundreds of MB written once: it is
/// allocated first and marked for transparent huge pages (where the kernel offers them on
/// request), so that the zero fill takes one page fault per 2 MB instead of one per 4 kB.
template <typename T>
void zeroFilled(std::vector<T>& v, std::int64_t n) {
  v.reserve(static_cast<std::size_t>(n));
#ifdef __linux__
  constexpr std::uintptr_t kHugePage = std::uintptr_t{1} << 21;
  const auto begin = reinterpret_cast<std::uintptr_t>(v.data());
  const std::uintptr_t first = (begin + kHugePage - 1) & ~(kHugePage - 1);
  const std::uintptr_t last =
      (begin + static_cast<std::uintptr_t>(n) * sizeof(T)) & ~(kHugePage - 1);
  if (last > first) {
    madvise(reinterpret_cast<void*>(first), last - first, MADV_HUGEPAGE);  // advice only
  }
#endif
  v.assign(static_cast<std::size_t>(n), T{});
}

}  // namespace

PolicyTable solveValueIteration(const SteeringModel& model, const SolverOptions& options,
                                SolveStats* stats) {
  if (!(options.epsilon > 0.0) || !std::isfinite(options.epsilon)) {
    throw std::invalid_argument("solveValueIteration: epsilon must be finite and > 0, got " +
                                std::to_string(options.epsilon));
  }
  if (options.max_sweeps < 1) {
    throw std::invalid_argument("solveValueIteration: max_sweeps must be >= 1, got " +
                                std::to_string(options.max_sweeps));
  }
  if (options.threads < 1) {
    throw std::invalid_argument("solveValueIteration: threads must be >= 1, got " +
                                std::to_string(options.threads));
  }
  if (!(options.skip_fraction >= 0.0 && options.skip_fraction <= 1.0)) {
    throw std::invalid_argument("solveValueIteration: skip_fraction must be in [0, 1], got " +
                                std::to_string(options.skip_fraction));
  }
  const auto t0 = std::chrono::steady_clock::now();
  const GridSpec& g = model.grid();
  const int nc = g.nc;
  const std::int64_t n = g.numStates();
  std::vector<float> values;
  std::vector<std::uint8_t> controls;
  zeroFilled(values, n);
  zeroFilled(controls, n);
  const std::vector<std::uint8_t>& cells = model.cells();
  for (std::int64_t pos = 0; pos < g.numPositions(); ++pos) {
    if (model.cell(pos) == Cell::kTarget) {
      std::fill_n(values.begin() + pos * 2 * nc, 2 * nc, 1.0f);
    }
  }
  std::vector<const StencilEntry*> begins(static_cast<std::size_t>(4 * nc)),
      ends(static_cast<std::size_t>(4 * nc));
  for (int b = 0; b < 2; ++b) {
    for (int k = 0; k < nc; ++k) {
      for (int u = 0; u < 2; ++u) {
        const auto slot = static_cast<std::size_t>((b * nc + k) * 2 + u);
        begins[slot] = model.stencilBegin(k, static_cast<Bevel>(b), static_cast<Control>(u));
        ends[slot] = model.stencilEnd(k, static_cast<Bevel>(b), static_cast<Control>(u));
      }
    }
  }

  // Bands of rows, one per thread; a band at least as tall as the stencil's reach.
  const int reach = model.maxRowReach();
  const int n_threads = std::max(1, std::min(options.threads, g.ny / std::max(1, 2 * reach)));
  std::vector<Band> bands;
  for (int t = 0; t < n_threads; ++t) {
    bands.push_back({g.ny * t / n_threads, g.ny * (t + 1) / n_threads, t});
  }
  // Left uninitialised: only the rows copied at the start of each sweep are ever read, so only
  // their pages are touched.
  std::unique_ptr<float[]> snapshot(n_threads > 1 ? new float[static_cast<std::size_t>(n)]
                                                  : nullptr);
  // Every position is copied before the first sweep, then only those updated since.
  std::vector<std::uint8_t> unsaved(
      n_threads > 1 ? static_cast<std::size_t>(g.numPositions()) : std::size_t{0}, 1);

  Context c;
  c.model = &model;
  c.grid = &g;
  c.cells = cells.data();
  c.values = values.data();
  c.snapshot = snapshot.get();
  c.controls = controls.data();
  c.stencil_begin = begins.data();
  c.stencil_end = ends.data();
  c.split = model.transitionModel() == TransitionModel::kInterpolated;
  ArcTables arc_tables = c.split ? arcTables(model) : ArcTables{};
  if (c.split) {
    prefetchLines(arc_tables, values.data(), nc);
  }
  c.arcs = &arc_tables;
  c.unsaved = n_threads > 1 ? unsaved.data() : nullptr;
  ChangeTracker tracker;
  if (options.skip_fraction > 0.0) {
    tracker = changeTracker(model, static_cast<float>(options.epsilon * options.skip_fraction),
                            n_threads);
    c.changes = &tracker;
  }

  SolveStats local;
  SolveStats& st = stats ? *stats : local;
  st = SolveStats{};
  int quiet_sweeps = 0;  // consecutive sweeps with max change < epsilon
  std::vector<float> band_change(static_cast<std::size_t>(n_threads), 0.0f);
  std::vector<std::int64_t> band_updates(static_cast<std::size_t>(n_threads), 0);
  for (int sweep = 0; sweep < options.max_sweeps; ++sweep) {
    const int order = sweep % kSweepOrders;
    const bool x_desc = order < 2;  // insertion is mostly along +x: start there
    const bool y_desc = order == 0 || order == 3;
    if (n_threads > 1) {
      copyBoundaryRows(g, bands, reach, values.data(), snapshot.get(), unsaved.data());
      std::vector<std::thread> pool;
      for (int t = 1; t < n_threads; ++t) {
        pool.emplace_back([&, t] {
          band_change[static_cast<std::size_t>(t)] =
              sweepBand(c, bands[static_cast<std::size_t>(t)], x_desc, y_desc, reach, true,
                        band_updates[static_cast<std::size_t>(t)]);
        });
      }
      band_change[0] = sweepBand(c, bands[0], x_desc, y_desc, reach, true, band_updates[0]);
      for (auto& th : pool) {
        th.join();
      }
    } else {
      band_change[0] = sweepBand(c, bands[0], x_desc, y_desc, reach, false, band_updates[0]);
    }
    if (c.changes != nullptr) {
      tracker.endSweep();
    }
    const double max_change = *std::max_element(band_change.begin(), band_change.end());
    st.max_change_per_sweep.push_back(max_change);
    st.updated_per_sweep.push_back(
        std::accumulate(band_updates.begin(), band_updates.end(), std::int64_t{0}));
    st.sweeps = sweep + 1;
    st.last_max_change = max_change;
    quiet_sweeps = max_change < options.epsilon ? quiet_sweeps + 1 : 0;
    // Converged when a full cycle of orders changed nothing by epsilon: a single quiet sweep
    // in an order that runs against the flow of information would prove little.
    if (quiet_sweeps >= kSweepOrders) {
      st.converged = true;
      break;
    }
  }

  std::vector<std::uint64_t> bits(static_cast<std::size_t>((n + 63) / 64), 0);
  for (std::int64_t s = 0; s < n; ++s) {
    if (controls[static_cast<std::size_t>(s)]) {
      bits[static_cast<std::size_t>(s >> 6)] |= std::uint64_t{1} << (s & 63);
    }
  }
  st.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return PolicyTable(g, model.hash(), std::move(values), std::move(bits), cells, options.epsilon,
                     st.sweeps, st.converged);
}

}  // namespace needle_guidance::steering
