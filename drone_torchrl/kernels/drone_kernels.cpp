// CPU kernels of the fast engine: whole-episode rollouts of many agents' three-net policies on the
// drone's dynamics (sampling included), and one REINFORCE update's loss gradient through them.
// Built and loaded by drone_torchrl/kernels/build.py and exposed as torch.library ops by
// drone_torchrl/kernels/ops.py; the PyTorch code they replace (envs/dynamics.py,
// modules/stacked.py, training/rng.py, objectives/reinforce.py) stays the reference they are
// tested against.
//
// Why hand-written: per update the engine evaluates a 6-32-32-4 network up to 300 times in a
// sequential loop for each agent and then differentiates it over the stored steps. PyTorch runs
// each of those as dozens of dispatcher calls on tiny tensors (5-20 us each on a 2-core machine),
// and torch.compile needs half a minute of compilation per process to fuse them (with new
// compilations as episode lengths change). Here one call does a whole update's rollout and
// gradient in SIMD registers.
//
// Layout: 8 float32 (or 4 float64) rows are processed together, one per SIMD lane, with GCC's
// vector extensions (portable: the compiler picks the machine's instructions). Every lane runs
// the same instructions, so a row's numbers do not depend on which lane or block it falls in:
// an agent's rollout and gradient are the same alone and inside any population.
//
// Parameters of one agent are one flat vector in ThreeNetPolicy.named_parameters() order:
// for each hidden layer weight [out, in] then bias [out], then the mean head (weight [2, h], bias
// [2]) and the std head (the same shapes).

#include <cmath>
#include <cstdint>
#include <cstring>
#include <thread>
#include <type_traits>
#include <vector>

namespace {

constexpr int kVectorBytes = 32;

// One build per precision (drone_torchrl/kernels/build.py compiles float64 only when a run asks
// for it): the scalar type of every tensor the C interface takes.
#ifndef DK_DOUBLE
#define DK_DOUBLE 0
#endif
using Real = std::conditional_t<DK_DOUBLE != 0, double, float>;
constexpr int kMaxLayers = 16;
constexpr int kMaxWidth = 1024;
constexpr int kStateDim = 6;
constexpr int kActionDim = 2;

// GCC's vector extensions cannot take a template parameter's type directly: one typedef each.
template <class S>
struct VecOf;
template <>
struct VecOf<float> {
  typedef float type __attribute__((vector_size(kVectorBytes)));
};
template <>
struct VecOf<double> {
  typedef double type __attribute__((vector_size(kVectorBytes)));
};
template <class S>
using Vec = typename VecOf<S>::type;

template <class S>
constexpr int lanes() {
  return kVectorBytes / sizeof(S);
}

template <class S>
inline Vec<S> splat(S x) {
  return Vec<S>{} + x;
}

// Helpers are templates over the vector type V (a Vec<S> cannot deduce S).
template <class V>
inline V vabs(V a) {
  return a < 0 ? -a : a;
}

// Like torch.clamp: NaN stays NaN (a plain min/max would replace it by a bound).
template <class V, class S>
inline V clamp(V x, S lo, S hi) {
  return x < lo ? V{} + lo : (x > hi ? V{} + hi : x);
}

// ------------------------------------------------------------------------------------------------
// Elementary functions on vectors. float32: polynomial approximations within a few ulp (Cephes'
// and Eigen's coefficients), so they vectorise; float64: the C library per lane.

using F = Vec<float>;
using I32 = int32_t __attribute__((vector_size(kVectorBytes)));

inline F exp_f(F x0) {
  F x = clamp(x0, -87.3365448f, 88.0f);
  F n = x * 1.44269504088896341f + 0.5f;
  I32 ni = __builtin_convertvector(n, I32);
  ni -= (__builtin_convertvector(ni, F) > n) & 1;  // floor
  F fn = __builtin_convertvector(ni, F);
  x = x - fn * 0.693359375f;
  x = x - fn * -2.12194440e-4f;
  F z = x * x;
  F y = splat(1.9875691500e-4f);
  y = y * x + 1.3981999507e-3f;
  y = y * x + 8.3334519073e-3f;
  y = y * x + 4.1665795894e-2f;
  y = y * x + 1.6666665459e-1f;
  y = y * x + 5.0000001201e-1f;
  y = y * z + x + 1.0f;
  I32 bits = (ni + 127) << 23;
  F scale;
  std::memcpy(&scale, &bits, sizeof scale);
  return x0 == x0 ? y * scale : x0;
}

// log(x) for x > 0 (Cephes logf).
inline F log_f(F x) {
  I32 bits;
  std::memcpy(&bits, &x, sizeof bits);
  I32 e = ((bits >> 23) & 0xff) - 126;
  bits = (bits & 0x807fffff) | 0x3f000000;  // mantissa in [0.5, 1)
  F m;
  std::memcpy(&m, &bits, sizeof m);
  auto small = m < 0.707106781186547524f;
  e -= small & 1;
  m = small ? m + m - 1.0f : m - 1.0f;
  F z = m * m;
  F y = splat(7.0376836292e-2f);
  y = y * m - 1.1514610310e-1f;
  y = y * m + 1.1676998740e-1f;
  y = y * m - 1.2420140846e-1f;
  y = y * m + 1.4249322787e-1f;
  y = y * m - 1.6668057665e-1f;
  y = y * m + 2.0000714765e-1f;
  y = y * m - 2.4999993993e-1f;
  y = y * m + 3.3333331174e-1f;
  y = y * m * z;
  F fe = __builtin_convertvector(e, F);
  y = y + fe * -2.12194440e-4f;
  y = y - 0.5f * z;
  return x == x ? m + y + fe * 0.693359375f : x;
}

inline F sqrt_f(F x) {
  for (int l = 0; l < 8; l++) x[l] = std::sqrt(x[l]);  // compiles to one vector square root
  return x;
}

// log(1 + x) for x >= 0, accurate for small x (Goldberg's trick on log_f).
inline F log1p_f(F x) {
  F u = x + 1.0f;
  F d = u - 1.0f;
  return d == 0 ? x : log_f(u) * (x / d);
}

inline F tanh_f(F x) {
  // Eigen's rational approximation (ptanh_float), exact to a few ulp over [-7.9, 7.9].
  x = clamp(x, -7.90531110763549805f, 7.90531110763549805f);
  F x2 = x * x;
  F p = splat(-2.76076847742355e-16f);
  p = p * x2 + 2.00018790482477e-13f;
  p = p * x2 - 8.60467152213735e-11f;
  p = p * x2 + 5.12229709037114e-08f;
  p = p * x2 + 1.48572235717979e-05f;
  p = p * x2 + 6.37261928875436e-04f;
  p = p * x2 + 4.89352455891786e-03f;
  p = p * x;
  F q = splat(1.19825839466702e-06f);
  q = q * x2 + 1.18534705686654e-04f;
  q = q * x2 + 2.26843463243900e-03f;
  q = q * x2 + 4.89352518554385e-03f;
  return vabs(x) < 0.0004f ? x : p / q;
}

// sin and cos (Cephes sinf/cosf: reduction by pi/4 in three parts, then the octant's polynomial).
inline void sincos_f(F x0, F* s, F* c) {
  F x = x0;
  F sign_s = x < 0 ? splat(-1.0f) : splat(1.0f);
  x = vabs(x);
  I32 j = __builtin_convertvector(x * 1.27323954473516f, I32);
  j = (j + 1) & ~1;
  F y = __builtin_convertvector(j, F);
  F r = ((x - y * 0.78515625f) - y * 2.4187564849853515625e-4f) - y * 3.77489497744594108e-8f;
  F z = r * r;
  F ps = ((-1.9515295891e-4f * z + 8.3321608736e-3f) * z - 1.6666654611e-1f) * z * r + r;
  F pc = ((2.443315711809948e-5f * z - 1.388731625493765e-3f) * z + 4.166664568298827e-2f) * z * z -
         0.5f * z + 1.0f;
  I32 swap = (j & 2) != 0;
  F sv = swap ? pc : ps;
  F cv = swap ? ps : pc;
  sign_s = ((j & 4) != 0) ? -sign_s : sign_s;
  F sign_c = (((j - 2) & 4) != 0) ? splat(1.0f) : splat(-1.0f);
  *s = sv * sign_s;
  *c = cv * sign_c;
  // Beyond 8192 the three-part reduction loses digits: those lanes (and NaN) go to the C library.
  const auto far = !(vabs(x0) < 8192.0f);
  bool any_far = false;
  for (int l = 0; l < 8; l++) any_far = any_far || far[l];
  if (any_far)
    for (int l = 0; l < 8; l++)
      if (far[l]) {
        (*s)[l] = std::sin(x0[l]);
        (*c)[l] = std::cos(x0[l]);
      }
}

template <class S, class Fn>
inline Vec<S> per_lane(Vec<S> x, Fn fn) {
  for (int l = 0; l < lanes<S>(); l++) x[l] = fn(x[l]);
  return x;
}

inline Vec<double> exp_v(Vec<double> x) { return per_lane<double>(x, [](double v) { return std::exp(v); }); }
inline Vec<double> log1p_v(Vec<double> x) { return per_lane<double>(x, [](double v) { return std::log1p(v); }); }
inline Vec<double> tanh_v(Vec<double> x) { return per_lane<double>(x, [](double v) { return std::tanh(v); }); }
inline void sincos_v(Vec<double> x, Vec<double>* s, Vec<double>* c) {
  *s = per_lane<double>(x, [](double v) { return std::sin(v); });
  *c = per_lane<double>(x, [](double v) { return std::cos(v); });
}
inline Vec<double> log_v(Vec<double> x) { return per_lane<double>(x, [](double v) { return std::log(v); }); }
inline F exp_v(F x) { return exp_f(x); }
inline F log_v(F x) { return log_f(x); }
inline F log1p_v(F x) { return log1p_f(x); }
inline F tanh_v(F x) { return tanh_f(x); }
inline void sincos_v(F x, F* s, F* c) { sincos_f(x, s, c); }

// ------------------------------------------------------------------------------------------------
// The network.

enum Activation { kTanh = 0, kRelu = 1, kElu = 2 };

struct Net {
  int in_dim;
  int n_hidden;
  int hidden[kMaxLayers];
  int activation;
  double min_std;
  // Added to the mean and to the std (ThreeNetPolicy's distribution_eps): Normal(mu + eps, sigma + eps).
  double dist_eps;
  // Where each layer's weight [out, in] starts in the flat vector (its bias follows it): the hidden
  // layers, then the mean head, then the std head. And each layer's input width.
  int offset[kMaxLayers + 2];
  int width[kMaxLayers + 2];
  int params;
  int activations;  // hidden outputs of one row

  int last() const { return width[n_hidden]; }
  int out(int l) const { return l < n_hidden ? hidden[l] : kActionDim; }
};

template <class V>
inline V activate(V x, int activation) {
  if (activation == kTanh) return tanh_v(x);
  if (activation == kRelu) return x < 0 ? V{} : x;
  return x > 0 ? x : exp_v(x) - 1;  // elu, alpha 1
}

// The derivative of the activation from its output y.
template <class V>
inline V activation_grad(V y, int activation) {
  if (activation == kTanh) return 1 - y * y;
  if (activation == kRelu) return y > 0 ? V{} + 1 : V{};
  return y > 0 ? V{} + 1 : y + 1;
}

// torch.nn.functional.softplus (beta 1, threshold 20).
template <class V>
inline V softplus(V x) {
  return x > 20 ? x : log1p_v(exp_v(x));
}

// out[o] = bias[o] + sum_i w[o * in + i] * x[i] for o < n, summed in order of i. Eight outputs at a
// time: eight independent accumulator chains keep the FMA units busy (one chain per output would
// wait on each FMA's latency). W is a vector (each lane its own agent's weights) or a scalar (every
// lane the same agent); per lane the arithmetic is the same.
template <class V, class W>
inline void matvec(const W* w, const W* bias, const V* x, int in, int n, V* out) {
  constexpr int kTile = 8;
  int o = 0;
  for (; o + kTile <= n; o += kTile) {
    V acc[kTile];
    for (int k = 0; k < kTile; k++) acc[k] = V{} + bias[o + k];
    for (int i = 0; i < in; i++) {
      const V xi = x[i];
      for (int k = 0; k < kTile; k++) acc[k] += w[(o + k) * in + i] * xi;
    }
    for (int k = 0; k < kTile; k++) out[o + k] = acc[k];
  }
  for (; o < n; o++) {
    V acc = V{} + bias[o];
    for (int i = 0; i < in; i++) acc += w[o * in + i] * x[i];
    out[o] = acc;
  }
}

// out[i] = sum_o w[o * in + i] * d[o] for i < in (the transposed product of matvec), eight at a time.
template <class V, class W>
inline void matvec_t(const W* w, const V* d, int n, int in, V* out) {
  constexpr int kTile = 8;
  int i = 0;
  for (; i + kTile <= in; i += kTile) {
    V acc[kTile] = {};
    for (int o = 0; o < n; o++) {
      const V d_o = d[o];
      for (int k = 0; k < kTile; k++) acc[k] += w[o * in + i + k] * d_o;
    }
    for (int k = 0; k < kTile; k++) out[i + k] = acc[k];
  }
  for (; i < in; i++) {
    V acc = V{};
    for (int o = 0; o < n; o++) acc += w[o * in + i] * d[o];
    out[i] = acc;
  }
}

// The forward pass of a block of rows from inputs x: the hidden outputs (acts, layer after layer),
// loc, and the std head's pre-activation.
template <class V, class W>
inline void forward(const Net& net, const W* w, const V* x, V* acts, V* loc, V* pre_std) {
  const V* input = x;
  V* out = acts;
  for (int l = 0; l < net.n_hidden; l++) {
    const int n = net.hidden[l], in = net.width[l];
    matvec(w + net.offset[l], w + net.offset[l] + n * in, input, in, n, out);
    for (int o = 0; o < n; o++) out[o] = activate(out[o], net.activation);
    input = out;
    out += n;
  }
  const int in = net.last();
  for (int head = 0; head < 2; head++) {
    const W* hw = w + net.offset[net.n_hidden + head];
    matvec(hw, hw + kActionDim * in, input, in, kActionDim, head == 0 ? loc : pre_std);
  }
}

// The backward of one block, first pass: the gradient of every hidden layer's pre-activation
// (deltas, layer after layer like acts) from d_loc and d_pre (the std head's pre-activation).
template <class V, class W>
inline void backward_deltas(const Net& net, const W* w, const V* acts, const V* d_loc, const V* d_pre,
                            V* deltas) {
  if (net.n_hidden == 0) return;
  int act_offset[kMaxLayers], aoff = 0;
  for (int l = 0; l < net.n_hidden; l++) {
    act_offset[l] = aoff;
    aoff += net.hidden[l];
  }
  // d(last hidden output) = Wm^T d_loc + Ws^T d_pre, then through the activation.
  const int top = net.n_hidden - 1, n_top = net.hidden[top];
  const W* wm = w + net.offset[net.n_hidden];
  const W* ws = w + net.offset[net.n_hidden + 1];
  V* d = deltas + act_offset[top];
  V from_std[kMaxWidth];
  matvec_t(wm, d_loc, kActionDim, n_top, d);
  matvec_t(ws, d_pre, kActionDim, n_top, from_std);
  for (int i = 0; i < n_top; i++)
    d[i] = (d[i] + from_std[i]) * activation_grad(acts[act_offset[top] + i], net.activation);
  for (int l = top; l > 0; l--) {
    const int n = net.hidden[l], n_in = net.width[l];
    const W* wl = w + net.offset[l];
    const V* dl = deltas + act_offset[l];
    V* below = deltas + act_offset[l - 1];
    matvec_t(wl, dl, n, n_in, below);
    for (int i = 0; i < n_in; i++) below[i] *= activation_grad(acts[act_offset[l - 1] + i], net.activation);
  }
}

// The backward's second pass for one layer: grad_w[o, i] += sum over blocks of d[o] * in[i] (per lane),
// grad_b[o] += sum of d[o], over `blocks` blocks whose vectors are `d_stride` and `in_stride` apart.
// Four by four outputs and inputs at a time, so each loaded vector feeds four FMAs.
template <class V>
inline void weight_grad(const V* d, int d_stride, const V* in, int in_stride, int n, int n_in, int64_t blocks,
                        V* grad_w, V* grad_b) {
  constexpr int kTile = 4;
  for (int o0 = 0; o0 < n; o0 += kTile) {
    const int no = n - o0 < kTile ? n - o0 : kTile;
    for (int i0 = 0; i0 < n_in; i0 += kTile) {
      const int ni = n_in - i0 < kTile ? n_in - i0 : kTile;
      V acc[kTile][kTile] = {};
      for (int64_t b = 0; b < blocks; b++) {
        const V* db = d + b * d_stride + o0;
        const V* ib = in + b * in_stride + i0;
        for (int a = 0; a < no; a++)
          for (int c = 0; c < ni; c++) acc[a][c] += db[a] * ib[c];
      }
      for (int a = 0; a < no; a++)
        for (int c = 0; c < ni; c++) grad_w[(o0 + a) * n_in + i0 + c] += acc[a][c];
    }
    for (int a = 0; a < no; a++) {
      V acc = V{};
      for (int64_t b = 0; b < blocks; b++) acc += d[b * d_stride + o0 + a];
      grad_b[o0 + a] += acc;
    }
  }
}

// ------------------------------------------------------------------------------------------------
// The drone (envs/dynamics.py; eqs. 2.1-2.3 of the paper, semi-implicit Euler).

// Env constants, in the order drone_torchrl/kernels/ops.py packs them.
enum EnvConst {
  kWeight, kMass, kGravity, kDt, kArmOverInertia, kMaxThrust /* < 0: unbounded */, kXLimit, kZMin, kZMax,
  kAlphaLimit, kFloor /* z_min - floor_tolerance */, kZoneX, kZoneZMin, kZoneZMax, kRewardZone, kRewardAlive,
  kRewardTerminated, kSquashHigh /* tanh_normal's high; < 0: normal head */,
  kResetAir /* 1: start around the zone's centre; 0: on the floor */, kResetNoise, kZoneZCentre,
  kStrict /* 1: a state on a bound is outside (the domain and the zone); 0: inside */, kEnvConsts
};

// ------------------------------------------------------------------------------------------------
// The counter-based random numbers of drone_torchrl/training/rng.py (SplitMix64's finaliser on
// (seed, update counter, stream, index)): the same 64-bit integers, so the same uniforms exactly;
// the normals' Box-Muller arithmetic (log, cos, sin) agrees with PyTorch's to a few ulp.

constexpr uint64_t kGolden = 0x9E3779B97F4A7C15ull, kMix1 = 0xBF58476D1CE4E5B9ull, kMix2 = 0x94D049BB133111EBull;
constexpr uint64_t kUpdate = 0xD1B54A32D192ED03ull, kStream = 0xAEF17502108EF2D9ull;
constexpr uint64_t kStartStates = 1, kActionNoise = 2;  // rng.START_STATES, rng.ACTION_NOISE
constexpr int kUniformBits = 24;

inline uint64_t mix(uint64_t x) {
  x = (x ^ (x >> 30)) * kMix1;
  x = (x ^ (x >> 27)) * kMix2;
  return x ^ (x >> 31);
}

inline uint64_t stream_key(uint64_t seed, uint64_t counter, uint64_t stream) {
  return mix(mix(seed) ^ (counter * kUpdate + stream * kStream));
}

// rng.uniform's element `index` of the stream `key`: in (0, 1), exact in float32.
inline float uniform(uint64_t key, uint64_t index) {
  const uint64_t top = mix(key + index * kGolden) >> (64 - kUniformBits);
  return (static_cast<float>(top) + 0.5f) / static_cast<float>(1u << kUniformBits);
}

// TerminationCause codes.
constexpr int kOutX = 1, kFloorHit = 2, kCeiling = 3, kTilt = 4;

template <class S>
struct Block {
  std::vector<Vec<S>> w, acts, x;
  explicit Block(const Net& net)
      : w(net.params), acts(net.activations > 0 ? net.activations : 1), x(net.in_dim) {}
};

template <class S>
void pack_weights(const Net& net, const S* params, const int64_t* agent, int count, Vec<S>* w) {
  const int p = net.params;
  for (int l = 0; l < lanes<S>(); l++) {
    const S* src = params + agent[l < count ? l : 0] * p;
    for (int k = 0; k < p; k++) w[k][l] = src[k];
  }
}

struct RolloutArgs {
  int64_t rows, episodes, steps;
  const void* params;
  const void* start;
  const void* noise;  // null: deterministic (the mean action), unless rng is given
  const int64_t* rng;  // [rows, 2]: the row's agent's seed and update counter; start and noise are then drawn here
  const uint8_t* active;
  const double* env;
  const double* gamma;  // [agents]: the discount of each agent's returns-to-go
  void* obs;
  void* action;
  void* reward;
  int64_t* cause;
  int64_t* length;
  void* returns;  // [rows, steps]: sum_{k >= t} gamma^(k - t) reward_k over the row's episode
  double* stats;  // [rows, kStats]
  // Optional: what the REINFORCE gradient needs of every step, in lane vectors per agent (Saved).
  void* saved;
};

// Where the gradient pass finds each step: an agent's steps r = episode * steps + t go in blocks of
// L lanes (block r / L, lane r % L), each block W vectors: the observation, the hidden outputs,
// loc, the std head's pre-activation, the action and the return-to-go.
struct Saved {
  int in_dim, activations, width;  // width: vectors per block
  int64_t blocks;                  // per agent
  int x() const { return 0; }
  int acts() const { return in_dim; }
  int loc() const { return in_dim + activations; }
  int pre() const { return loc() + kActionDim; }
  int action() const { return pre() + kActionDim; }
  int ret() const { return action() + kActionDim; }
  static Saved of(const Net& net, int64_t episodes, int64_t steps, int lanes) {
    Saved s{};
    s.in_dim = net.in_dim;
    s.activations = net.activations;
    s.width = net.in_dim + net.activations + 3 * kActionDim + 1;
    s.blocks = (episodes * steps + lanes - 1) / lanes;
    return s;
  }
};

// Per-row counts for the episode metrics (drone_torchrl/episodes.py's definitions): the return,
// the steps that ended inside the target zone without terminating, the negative motor commands,
// and the termination cause of the last step.
enum Stat { kReturn, kZoneSteps, kNegative, kLastCause, kStats };

template <class S>
void rollout_blocks(const Net& net, const RolloutArgs& a, int64_t first, int64_t last) {
  constexpr int L = lanes<S>();
  const S* params = static_cast<const S*>(a.params);
  const S* start = static_cast<const S*>(a.start);
  const S* noise = static_cast<const S*>(a.noise);
  S* obs = static_cast<S*>(a.obs);
  S* action = static_cast<S*>(a.action);
  S* reward = static_cast<S*>(a.reward);
  S* saved = static_cast<S*>(a.saved);
  const Saved layout = Saved::of(net, a.episodes, a.steps, L);
  // The scalar of vector k of agent n's step r in the saved buffer.
  auto slot = [&](int64_t n, int64_t r, int k) -> S& {
    return saved[((n * layout.blocks + r / L) * layout.width + k) * L + r % L];
  };
  const double* env = a.env;
  const S weight = env[kWeight], mass = env[kMass], gravity = env[kGravity], dt = env[kDt];
  const S arm_over_inertia = env[kArmOverInertia], max_thrust = env[kMaxThrust];
  const S x_limit = env[kXLimit], z_min = env[kZMin], z_max = env[kZMax], alpha_limit = env[kAlphaLimit];
  const S floor = env[kFloor], zone_x = env[kZoneX], zone_z_min = env[kZoneZMin], zone_z_max = env[kZoneZMax];
  const S r_zone = env[kRewardZone], r_alive = env[kRewardAlive], r_term = env[kRewardTerminated];
  const S high = env[kSquashHigh], half = high / S(2);
  const S min_std = net.min_std, dist_eps = net.dist_eps;
  const S squash_lim = S(1) - (sizeof(S) == 4 ? S(1e-6) : S(1e-15));  // TorchRL's safe tanh
  // dynamics.termination_cause: beyond an upper (lower) bound is > (<), or >= (<=) with strict
  // bounds. dynamics.in_target_zone: within an upper (lower) bound is <= (>=), or < (>) strict.
  // (Each written out: a negated comparison would count NaN as inside the zone.)
  const bool strict = env[kStrict] > 0;
  const auto above = [strict](Vec<S> v, S bound) { return strict ? v >= bound : v > bound; };
  const auto below = [strict](Vec<S> v, S bound) { return strict ? v <= bound : v < bound; };
  const auto under = [strict](Vec<S> v, S bound) { return strict ? v < bound : v <= bound; };
  const auto over = [strict](Vec<S> v, S bound) { return strict ? v > bound : v >= bound; };
  Block<S> block(net);
  const int64_t T = a.steps;
  for (int64_t b = first; b < last; b++) {
    const int64_t row0 = b * L;
    const int count = static_cast<int>(row0 + L <= a.rows ? L : a.rows - row0);
    int64_t agent[L];
    bool live[L];
    for (int l = 0; l < L; l++) {
      agent[l] = (row0 + (l < count ? l : 0)) / a.episodes;
      live[l] = l < count && a.active[agent[l]];
    }
    for (int l = 0; l < count; l++) {
      a.length[row0 + l] = 0;
      for (int k = 0; k < kStats; k++) a.stats[(row0 + l) * kStats + k] = 0;
    }
    bool any = false;
    for (int l = 0; l < L; l++) any = any || live[l];
    if (!any) continue;
    pack_weights<S>(net, params, agent, L, block.w.data());
    Vec<S> s[kStateDim];
    // The stream keys of each lane's agent, and the row's episode index within its agent.
    uint64_t noise_key[L], episode[L];
    for (int l = 0; l < L; l++) {
      const int64_t row = row0 + (l < count ? l : 0);
      episode[l] = row % a.episodes;
      if (a.rng) {
        const uint64_t seed = a.rng[2 * row], counter = a.rng[2 * row + 1];
        noise_key[l] = stream_key(seed, counter, kActionNoise);
        const uint64_t start_key = stream_key(seed, counter, kStartStates);
        for (int k = 0; k < kStateDim; k++) {  // dynamics.states_from_uniform
          // The noise in float32, then the start point (the zone's centre or the floor) in S.
          const bool air = env[kResetAir] > 0;
          const float u = uniform(start_key, episode[l] * kStateDim + k);
          const float jitter = (2.0f * u - 1.0f) * static_cast<float>(env[kResetNoise]);
          const bool kept = air || k == 0 || k == 4;  // floor: x and alpha only
          const S base = k != 2 ? S(0) : air ? S(env[kZoneZCentre]) : z_min;
          s[k][l] = (kept ? S(jitter) : S(0)) + base;
        }
      } else {
        for (int k = 0; k < kStateDim; k++) s[k][l] = start[row * kStateDim + k];
      }
    }
    const bool stochastic = noise || a.rng;
    for (int64_t t = 0; t < T && any; t++) {
      for (int k = 0; k < kStateDim; k++) block.x[k] = s[k];
      Vec<S> loc[kActionDim], pre[kActionDim], act[kActionDim];
      forward(net, block.w.data(), block.x.data(), block.acts.data(), loc, pre);
      if (dist_eps != 0)
        for (int m = 0; m < kActionDim; m++) loc[m] = loc[m] + dist_eps;  // kept (saved) shifted
      Vec<S> z[kActionDim]{};
      if (a.rng) {  // rng.normal: one Box-Muller pair per step and episode, its two outputs the two motors
        F u1, u2;
        for (int l = 0; l < 8; l++) {
          const int lane = l < L ? l : 0;
          const uint64_t pair = static_cast<uint64_t>(t) * a.episodes + episode[lane];
          u1[l] = uniform(noise_key[lane], 2 * pair);
          u2[l] = uniform(noise_key[lane], 2 * pair + 1);
        }
        const F radius = sqrt_f(-2.0f * log_f(u1));
        F sin_a, cos_a;
        sincos_f(6.28318530717958647692f * u2, &sin_a, &cos_a);
        const F z0 = radius * cos_a, z1 = radius * sin_a;
        for (int l = 0; l < L; l++) {
          z[0][l] = z0[l];
          z[1][l] = z1[l];
        }
      } else if (noise) {
        for (int m = 0; m < kActionDim; m++)
          for (int l = 0; l < L; l++) z[m][l] = live[l] ? noise[((row0 + l) * T + t) * kActionDim + m] : S(0);
      }
      for (int m = 0; m < kActionDim; m++) {
        Vec<S> u = loc[m];
        if (stochastic) u = loc[m] + (softplus(pre[m]) + min_std + dist_eps) * z[m];
        if (high > 0) {
          Vec<S> th = tanh_v(u);
          th = clamp(th, -squash_lim, squash_lim);
          u = half + half * th;
        }
        act[m] = u;
      }
      // dynamics.step: clamp, integrate, termination cause, reward.
      Vec<S> a_l = act[0], a_r = act[1];
      if (max_thrust >= 0) {
        a_l = clamp(a_l, S(0), max_thrust);
        a_r = clamp(a_r, S(0), max_thrust);
      }
      const Vec<S> thrust_l = a_l * weight, thrust_r = a_r * weight, total = thrust_l + thrust_r;
      Vec<S> sin_a, cos_a;
      sincos_v(s[4], &sin_a, &cos_a);
      const Vec<S> x_ddot = -sin_a * total / mass;
      const Vec<S> z_ddot = cos_a * total / mass - gravity;
      const Vec<S> alpha_ddot = (thrust_r - thrust_l) * arm_over_inertia;
      Vec<S> n[kStateDim];
      n[1] = s[1] + x_ddot * dt;
      n[3] = s[3] + z_ddot * dt;
      n[5] = s[5] + alpha_ddot * dt;
      n[0] = s[0] + n[1] * dt;
      n[2] = s[2] + n[3] * dt;
      n[4] = s[4] + n[5] * dt;
      const Vec<S> ax = vabs(n[0]), aa = vabs(n[4]);
      // The lowest non-zero code wins: assign from the highest down.
      auto cause = above(aa, alpha_limit) & kTilt;
      cause = above(n[2], z_max) ? kCeiling : cause;
      cause = below(n[2], floor) ? kFloorHit : cause;
      cause = above(ax, x_limit) ? kOutX : cause;
      const auto zone =
          under(ax, zone_x) & over(n[2], zone_z_min) & under(n[2], zone_z_max) & under(aa, alpha_limit);
      Vec<S> r = zone ? splat(r_zone) : splat(r_alive);
      r = cause != 0 ? splat(r_term) : r;
      any = false;
      for (int l = 0; l < count; l++) {
        if (!live[l]) continue;
        const int64_t row = row0 + l, at = row * T + t, state_at = row * (T + 1) + t;
        if (obs) {
          for (int k = 0; k < kStateDim; k++) {
            obs[state_at * kStateDim + k] = s[k][l];
            obs[(state_at + 1) * kStateDim + k] = n[k][l];
          }
        }
        if (action) {
          action[at * kActionDim] = act[0][l];
          action[at * kActionDim + 1] = act[1][l];
        }
        if (saved) {
          const int64_t r_agent = episode[l] * T + t;
          for (int k = 0; k < kStateDim; k++) slot(agent[l], r_agent, layout.x() + k) = s[k][l];
          for (int k = 0; k < net.activations; k++) slot(agent[l], r_agent, layout.acts() + k) = block.acts[k][l];
          for (int m = 0; m < kActionDim; m++) {
            slot(agent[l], r_agent, layout.loc() + m) = loc[m][l];
            slot(agent[l], r_agent, layout.pre() + m) = pre[m][l];
            slot(agent[l], r_agent, layout.action() + m) = act[m][l];
          }
        }
        reward[at] = r[l];
        a.cause[at] = cause[l];
        a.length[row] = t + 1;
        double* stat = a.stats + row * kStats;
        stat[kReturn] += r[l];
        stat[kZoneSteps] += zone[l] && cause[l] == 0;
        stat[kNegative] += (act[0][l] < 0) + (act[1][l] < 0);
        stat[kLastCause] = cause[l];
        live[l] = cause[l] == 0;
        any = any || live[l];
      }
      for (int k = 0; k < kStateDim; k++) s[k] = n[k];
    }
    // Returns-to-go of each row's episode, last step first (the loss's discounted_returns).
    for (int l = 0; l < count; l++) {
      const int64_t row = row0 + l;
      const S discount = a.gamma[agent[l]];
      S* out = static_cast<S*>(a.returns) + row * T;
      S running = 0;
      for (int64_t t = a.length[row] - 1; t >= 0; t--) {
        running = reward[row * T + t] + discount * running;
        out[t] = running;
        if (saved) slot(agent[l], episode[l] * T + t, layout.ret()) = running;
      }
    }
  }
}

// The loss options of drone_torchrl/objectives/reinforce.py (reinforce_terms), in this order.
struct LossOptions {
  int64_t baseline_mean, normalize_returns, discount_weight, mean_log_prob;
};

struct GradArgs {
  const RolloutArgs* roll;
  LossOptions options;
  void* grad;               // [agents, params]
  double* loss;             // [agents]: each agent's REINFORCE loss (reinforce_terms' loss_per_agent)
  double* std_mean;         // [agents]: the policy's mean std over the valid steps and motors
  uint8_t* actions_finite;  // [agents]
};

// The REINFORCE loss of each agent (ReinforceLoss: -sum_t w_t log pi(a_t | s_t) over its valid
// steps, divided by its episodes) and its gradient, from the steps the rollout saved: the
// log-probability's derivatives in loc and scale, then the network's backward through the saved
// hidden outputs (backward_deltas per block, weight_grad over the blocks). No forward pass again.
template <class S>
void reinforce_agents(const Net& net, const GradArgs& g, int64_t first, int64_t last) {
  constexpr int L = lanes<S>();
  using V = Vec<S>;
  const RolloutArgs& a = *g.roll;
  const LossOptions& o = g.options;
  const int64_t E = a.episodes, T = a.steps;
  const Saved layout = Saved::of(net, E, T, L);
  const int p = net.params, act_w = net.activations > 0 ? net.activations : 1;
  const S min_std = net.min_std, dist_eps = net.dist_eps, high = a.env[kSquashHigh], half = high / S(2);
  const S squash_lim = S(1) - (sizeof(S) == 4 ? S(1e-6) : S(1e-15));  // TorchRL's safe atanh
  const S half_log_2pi = S(0.91893853320467274178);                    // log(sqrt(2 pi))
  const S eps = sizeof(S) == 4 ? S(1.1920928955078125e-07) : S(2.220446049250313e-16);  // finfo eps
  std::vector<V> deltas(layout.blocks * act_w), heads(layout.blocks * 2 * kActionDim), grad(p);
  for (int64_t n = first; n < last; n++) {
    S* out = static_cast<S*>(g.grad) + n * p;
    g.loss[n] = 0;
    g.std_mean[n] = 0;
    g.actions_finite[n] = 1;
    for (int k = 0; k < p; k++) out[k] = 0;
    if (!a.active[n]) continue;
    V* saved = static_cast<V*>(a.saved) + n * layout.blocks * layout.width;
    const int64_t* length = a.length + n * E;
    // Lane masks of the valid steps, the blocks in use, and the per-agent sums of reinforce_terms.
    int64_t used = 0, episodes = 0, steps = 0;
    for (int64_t e = 0; e < E; e++) {
      if (length[e] > 0) used = (e * T + length[e] + L - 1) / L;
      episodes += length[e] > 0;
      steps += length[e];
    }
    if (episodes == 0) continue;
    auto valid = [&](int64_t b) {
      V mask{};
      for (int l = 0; l < L; l++) {
        const int64_t r = b * L + l, e = r / T;
        mask[l] = e < E && r % T < length[e] ? S(1) : S(0);
      }
      return mask;
    };
    // Steps past a row's end were never written: zero them so they add nothing (0 * garbage may be NaN).
    for (int64_t b = 0; b < used; b++) {
      const V mask = valid(b);
      for (int k = 0; k < layout.width; k++)
        saved[b * layout.width + k] = mask != 0 ? saved[b * layout.width + k] : V{};
    }
    S mean = 0, std = 0;
    if (o.baseline_mean || o.normalize_returns) {
      S total = 0;
      for (int64_t b = 0; b < used; b++)
        for (int l = 0; l < L; l++) total += saved[b * layout.width + layout.ret()][l];
      mean = total / S(steps);
      if (o.normalize_returns) {
        S squares = 0;
        for (int64_t b = 0; b < used; b++) {
          const V mask = valid(b);
          const V centred = (saved[b * layout.width + layout.ret()] - mean) * mask;
          for (int l = 0; l < L; l++) squares += centred[l] * centred[l];
        }
        std = std::sqrt(squares / S(steps));
      }
    }
    const S gamma = a.gamma[n], per_episode = S(1) / S(episodes);
    const S reduce = o.mean_log_prob ? S(1) / S(kActionDim) : S(1);
    S loss = 0, std_sum = 0;
    bool finite = true;
    for (int64_t b = 0; b < used; b++) {
      const V* blk = saved + b * layout.width;
      const V mask = valid(b);
      V w = blk[layout.ret()];
      if (o.baseline_mean || o.normalize_returns) w = w - mean;
      if (o.normalize_returns) w = w / (std + eps);
      if (o.discount_weight) {
        for (int l = 0; l < L; l++) w[l] *= std::pow(gamma, S((b * L + l) % T));
      }
      const V coef = -w * per_episode * mask;  // d loss / d log pi at each step
      V log_prob{};
      V* d_loc = &heads[b * 2 * kActionDim];
      V* d_pre = d_loc + kActionDim;
      for (int m = 0; m < kActionDim; m++) {
        const V pre = blk[layout.pre() + m], loc = blk[layout.loc() + m], action = blk[layout.action() + m];
        const V scale = softplus(pre) + min_std + dist_eps;
        V sample = action;
        if (high > 0) {  // TanhNormal: the Normal sample the action came from, as TorchRL inverts it
          const V y = clamp((action - half) / half, -squash_lim, squash_lim);
          sample = S(0.5) * (log1p_v(y) - log1p_v(-y));  // atanh
          // log |d action / d sample| of the tanh and the affine map (TanhTransform's formula).
          log_prob -= S(2) * (S(0.69314718055994530942) - sample - softplus(-S(2) * sample)) + std::log(half);
        }
        const V z = (sample - loc) / scale;
        log_prob += -S(0.5) * z * z - log_v(scale) - half_log_2pi;
        d_loc[m] = coef * reduce * z / scale;
        const V d_scale = coef * reduce * (z * z - S(1)) / scale;
        const V e = exp_v(pre);  // softplus' (beta 1, threshold 20): sigmoid below the threshold
        d_pre[m] = pre > S(20) ? d_scale : d_scale * e / (e + S(1));
        for (int l = 0; l < L; l++) {
          if (mask[l] == 0) continue;
          std_sum += scale[l];
          finite = finite && std::isfinite(action[l]);
        }
      }
      for (int l = 0; l < L; l++) loss += mask[l] != 0 ? coef[l] * reduce * log_prob[l] : S(0);
      backward_deltas(net, static_cast<const S*>(a.params) + n * p, blk + layout.acts(), d_loc, d_pre,
                      &deltas[b * act_w]);
    }
    // The weights' gradients, layer by layer, as sums over the blocks (weight_grad), then the lanes.
    for (int k = 0; k < p; k++) grad[k] = V{};
    int start = 0;
    for (int l = 0; l < net.n_hidden + 2; l++) {
      const int n_out = net.out(l), n_in = net.width[l];
      const int prev = l < net.n_hidden ? l - 1 : net.n_hidden - 1;
      const V* input = prev < 0 ? saved + layout.x() : saved + layout.acts() + start;
      const V* d = l < net.n_hidden ? deltas.data() + start + (l ? net.hidden[l - 1] : 0)
                                    : heads.data() + (l - net.n_hidden) * kActionDim;
      const int d_stride = l < net.n_hidden ? act_w : 2 * kActionDim;
      V* gw = grad.data() + net.offset[l];
      weight_grad(d, d_stride, input, layout.width, n_out, n_in, used, gw, gw + n_out * n_in);
      if (l > 0 && l < net.n_hidden) start += net.hidden[l - 1];
    }
    for (int k = 0; k < p; k++) {
      S sum = 0;
      for (int l = 0; l < L; l++) sum += grad[k][l];
      out[k] = sum;
    }
    g.loss[n] = loss;
    g.std_mean[n] = std_sum / S(steps * kActionDim);
    g.actions_finite[n] = finite;
  }
}

template <class Fn>
void parallel_blocks(int64_t blocks, int threads, Fn fn) {
  if (threads <= 1 || blocks < 2) {
    fn(0, blocks);
    return;
  }
  const int64_t workers = blocks < threads ? blocks : threads;
  std::vector<std::thread> pool;
  for (int64_t k = 0; k < workers; k++)
    pool.emplace_back(fn, blocks * k / workers, blocks * (k + 1) / workers);
  for (auto& th : pool) th.join();
}

Net make_net(int64_t in_dim, int64_t n_hidden, const int64_t* hidden, int64_t activation, double min_std,
             double dist_eps) {
  Net net{};
  net.in_dim = static_cast<int>(in_dim);
  net.n_hidden = static_cast<int>(n_hidden);
  net.activation = static_cast<int>(activation);
  net.min_std = min_std;
  net.dist_eps = dist_eps;
  int off = 0, in = net.in_dim;
  for (int l = 0; l < net.n_hidden + 2; l++) {
    const int n = l < net.n_hidden ? static_cast<int>(hidden[l]) : kActionDim;
    if (l < net.n_hidden) {
      net.hidden[l] = n;
      net.activations += n;
    }
    net.offset[l] = off;
    net.width[l] = in;
    off += n * in + n;
    if (l < net.n_hidden) in = n;
  }
  net.params = off;
  return net;
}

}  // namespace

extern "C" {

// How many drone constants the kernels read (drone_torchrl/kernels/ops.py: ENV_CONSTANTS).
int64_t dk_env_consts() { return kEnvConsts; }

// Whole episodes for rows = agents * episodes (row r flies agent r / episodes's policy): until each
// row's episode terminates or `steps` steps. Writes the states ([rows, steps + 1, 6]: before each
// step, and after the last), the action, the reward, the termination cause and the return-to-go
// of every step flown, each row's length and its Stat counts; entries after a row's end are left
// as they were (the caller zero-fills). Tensors hold Real numbers (the build's precision).
void dk_rollout(int64_t threads, int64_t in_dim, int64_t n_hidden, const int64_t* hidden, int64_t activation,
                double min_std, double dist_eps, int64_t rows, int64_t episodes, int64_t steps, const void* params,
                const void* start, const void* noise, const int64_t* rng, const uint8_t* active, const double* env,
                const double* gamma, void* obs, void* action, void* reward, int64_t* cause, int64_t* length,
                void* returns, double* stats) {
  const Net net = make_net(in_dim, n_hidden, hidden, activation, min_std, dist_eps);
  RolloutArgs a{rows,  episodes, steps,  params, start,  noise,  rng,     active,  env,
                gamma, obs,      action, reward, cause,  length, returns, stats,  nullptr};
  const int64_t blocks = (rows + lanes<Real>() - 1) / lanes<Real>();
  parallel_blocks(blocks, threads, [&](int64_t f, int64_t l) { rollout_blocks<Real>(net, a, f, l); });
}

// One REINFORCE update's episodes and gradient for every active agent: the rollout of dk_rollout
// (start states and noise drawn from rng), then reinforce_agents. options: LossOptions' four flags.
void dk_reinforce(int64_t threads, int64_t in_dim, int64_t n_hidden, const int64_t* hidden, int64_t activation,
                  double min_std, double dist_eps, int64_t agents, int64_t episodes, int64_t steps, const void* params,
                  const int64_t* rng, const uint8_t* active, const double* env, const double* gamma,
                  const int64_t* options, void* reward, int64_t* cause, int64_t* length, void* returns,
                  double* stats, void* saved, void* grad, double* loss, double* std_mean, uint8_t* actions_finite) {
  const Net net = make_net(in_dim, n_hidden, hidden, activation, min_std, dist_eps);
  const int64_t rows = agents * episodes;
  RolloutArgs a{rows,  episodes, steps,   params, nullptr, nullptr, rng,     active, env,
                gamma, nullptr,  nullptr, reward, cause,   length,  returns, stats,  saved};
  GradArgs g{&a, {options[0], options[1], options[2], options[3]}, grad, loss, std_mean, actions_finite};
  parallel_blocks((rows + lanes<Real>() - 1) / lanes<Real>(), threads,
                  [&](int64_t f, int64_t l) { rollout_blocks<Real>(net, a, f, l); });
  parallel_blocks(agents, threads, [&](int64_t f, int64_t l) { reinforce_agents<Real>(net, g, f, l); });
}

// The size of dk_reinforce's saved buffer, in scalars.
int64_t dk_saved_size(int64_t in_dim, int64_t n_hidden, const int64_t* hidden, int64_t agents, int64_t episodes,
                      int64_t steps) {
  const Net net = make_net(in_dim, n_hidden, hidden, kTanh, 0, 0);
  const Saved layout = Saved::of(net, episodes, steps, lanes<Real>());
  return agents * layout.blocks * layout.width * lanes<Real>();
}

// 4 (float32) or 8 (float64): the precision of this build's tensors, in bytes.
int64_t dk_real_bytes() { return sizeof(Real); }

}  // extern "C"
