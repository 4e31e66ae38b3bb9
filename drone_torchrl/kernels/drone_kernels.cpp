// The fast engine: whole-episode rollouts of many agents' three-net policies on the drone's
// dynamics (disturbances, sampling included), one REINFORCE update's loss gradient through them,
// and PPO/A2C's auto-resetting segments. Built and loaded by drone_torchrl/kernels/build.py and
// called from PyTorch through drone_torchrl/kernels/ops.py; the PyTorch code they replace
// (envs/dynamics.py, envs/disturbances.py, modules/stacked.py, envs/rng.py,
// objectives/reinforce.py, envs/drone_env.py) stays the reference they are tested against.
//
// Why hand-written: per update the engine evaluates a 6-32-32-4 network up to 300 times in a
// sequential loop for each agent and then differentiates it over the stored steps. PyTorch runs
// each of those as dozens of dispatcher calls on tiny tensors, each costing more than its arithmetic,
// and torch.compile needs half a minute of compilation per process to fuse them. Here one call
// does a whole update's rollout and gradient in SIMD registers.
//
// One definition, two targets. Each drone's step (physics with its disturbances, termination,
// reward), its observation, the policy's forward pass and sample, and the REINFORCE backward are
// written once below, as DK_HD functions templated on the lane type V:
// - the CPU loops (the end of this file) call them with V a GCC vector of 8 float32 (or 4 float64)
//   drones, one per SIMD lane; every lane runs the same instructions, so a drone's numbers do not
//   depend on its lane or block (an agent's run is the same alone and inside any population);
// - a CUDA kernel (one thread per drone) will call them with V = float or double.
// So those functions use no vector-only idiom: lanes through lane()/set_lane(), masks through
// select()/both()/lane_any(), elementary functions through overloads (float32 polynomials for
// vectors, the C library for scalars). build.scalar_check() (a test runs it) proves it: it
// compiles this file with -DDK_SCALAR_CHECK, which leaves out every vector type and instantiates
// the loops that call them, and so each of them, with V = float and V = double (the end of this file).
//
// Parameters of one agent are one flat vector in ThreeNetPolicy.named_parameters() order:
// for each hidden layer weight [out, in] then bias [out], then the mean head (weight [2, h], bias
// [2]) and the std head (the same shapes).

#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>

#if defined(__CUDACC__)
#define DK_HD __host__ __device__
#else
#define DK_HD
#endif
// The CPU engine (vector types, threads, the C interface): not in a CUDA build or the scalar check.
#if !defined(__CUDACC__) && !defined(DK_SCALAR_CHECK)
#define DK_CPU 1
#include <thread>
#include <vector>
#else
#define DK_CPU 0
#endif

namespace {

constexpr int kMaxLayers = 16;
constexpr int kMaxWidth = 1024;
constexpr int kStateDim = 6;
constexpr int kActionDim = 2;
constexpr int kMaxBack = 25;  // disturbances.MAX_STEPS_BACK: the longest delay and command memory

// ------------------------------------------------------------------------------------------------
// Lanes. V is a scalar (one drone) or, on the CPU, a GCC vector (one drone per lane).

template <class V>
struct LaneTraits {
  using Scalar = V;
  using Float = float;  // float32 lanes at least as many as V's (the training RNG's Box-Muller)
  static constexpr int kLanes = 1;
};
template <class V>
using ScalarOf = typename LaneTraits<V>::Scalar;
template <class V>
using FloatOf = typename LaneTraits<V>::Float;
template <class V>
DK_HD constexpr int lanes_of() {
  return LaneTraits<V>::kLanes;
}

template <class V>
DK_HD inline V splat(ScalarOf<V> x) {
  return V{} + x;
}
DK_HD inline bool lane_any(bool m) { return m; }
// A mask is what a comparison gives: bool for scalars, a vector of 0 / -1 for vectors.
template <class M, class V>
DK_HD inline V select(M m, V a, V b) {
  return m ? a : b;
}
template <class M>
DK_HD inline M both(M a, M b) {
  return a & b;
}

template <class V>
DK_HD inline V vabs(V a) {
  return select(a < 0, -a, a);
}

// Like torch.clamp: NaN stays NaN (a plain min/max would replace it by a bound).
template <class V, class S>
DK_HD inline V clamp(V x, S lo, S hi) {
  return select(x < lo, V{} + lo, select(x > hi, V{} + hi, x));
}

// A scalar is one lane; its elementary functions are the C library's (a CUDA build maps them to its own).
#define DK_SCALAR(S)                                          \
  DK_HD inline S lane(S x, int) { return x; }                 \
  DK_HD inline void set_lane(S& x, int, S v) { x = v; }       \
  DK_HD inline S exp_v(S x) { return std::exp(x); }           \
  DK_HD inline S log_v(S x) { return std::log(x); }           \
  DK_HD inline S log1p_v(S x) { return std::log1p(x); }       \
  DK_HD inline S tanh_v(S x) { return std::tanh(x); }         \
  DK_HD inline S sqrt_v(S x) { return std::sqrt(x); }         \
  DK_HD inline void sincos_v(S x, S* s, S* c) { *s = std::sin(x), *c = std::cos(x); }
DK_SCALAR(float)
DK_SCALAR(double)

#if DK_CPU
// ------------------------------------------------------------------------------------------------
// GCC's vector extensions (portable: the compiler picks the machine's instructions).

constexpr int kVectorBytes = 32;
using F = float __attribute__((vector_size(kVectorBytes)));
using D = double __attribute__((vector_size(kVectorBytes)));
using I32 = int32_t __attribute__((vector_size(kVectorBytes)));

// A vector of n lanes of S; its Box-Muller draws in float32 lanes (float64's lanes 4-7 unused).
#define DK_VECTOR(V, S, n)                               \
  template <>                                            \
  struct LaneTraits<V> {                                 \
    using Scalar = S;                                    \
    using Float = F;                                     \
    static constexpr int kLanes = n;                     \
  };                                                     \
  inline S lane(V x, int l) { return x[l]; }             \
  inline void set_lane(V& x, int l, S v) { x[l] = v; }
DK_VECTOR(F, float, 8)
DK_VECTOR(D, double, 4)
template <class M>
inline bool lane_any(M m) {
  bool any = false;
  for (unsigned l = 0; l < sizeof(M) / sizeof(m[0]); l++) any = any || m[l];
  return any;
}

// float64: the C library lane by lane (float32's square root too: one vector instruction).
#define DK_PER_LANE(V, name, fn)                                              \
  inline V name(V x) {                                                        \
    for (unsigned l = 0; l < sizeof(V) / sizeof(x[0]); l++) x[l] = fn(x[l]); \
    return x;                                                                 \
  }
DK_PER_LANE(F, sqrt_v, std::sqrt)
DK_PER_LANE(D, exp_v, std::exp)
DK_PER_LANE(D, log_v, std::log)
DK_PER_LANE(D, log1p_v, std::log1p)
DK_PER_LANE(D, tanh_v, std::tanh)
DK_PER_LANE(D, sqrt_v, std::sqrt)
inline void sincos_v(D x, D* s, D* c) {
  for (int l = 0; l < 4; l++) (*s)[l] = std::sin(x[l]), (*c)[l] = std::cos(x[l]);
}

// float32: polynomial approximations within a few ulp (Cephes' and Eigen's coefficients), so they
// vectorise. horner(x, c0, c1, ..., cn): c0 x^n + c1 x^(n-1) + ... + cn (the coefficients literals
// the compiler sees, as when written out).
template <class... C>
inline F horner(F x, float c0, C... c) {
  F y = splat<F>(c0);
  ((y = y * x + c), ...);
  return y;
}

inline F exp_v(F x0) {
  F x = clamp(x0, -87.3365448f, 88.0f);
  F n = x * 1.44269504088896341f + 0.5f;
  I32 ni = __builtin_convertvector(n, I32);
  ni -= (__builtin_convertvector(ni, F) > n) & 1;  // floor
  F fn = __builtin_convertvector(ni, F);
  x = x - fn * 0.693359375f;
  x = x - fn * -2.12194440e-4f;
  F z = x * x;
  F y = horner(x, 1.9875691500e-4f, 1.3981999507e-3f, 8.3334519073e-3f, 4.1665795894e-2f, 1.6666665459e-1f,
                   5.0000001201e-1f);
  y = y * z + x + 1.0f;
  I32 bits = (ni + 127) << 23;
  F scale;
  std::memcpy(&scale, &bits, sizeof scale);
  return x0 == x0 ? y * scale : x0;
}

// log(x) for x > 0 (Cephes logf).
inline F log_v(F x) {
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
  F y = horner(m, 7.0376836292e-2f, -1.1514610310e-1f, 1.1676998740e-1f, -1.2420140846e-1f, 1.4249322787e-1f,
                   -1.6668057665e-1f, 2.0000714765e-1f, -2.4999993993e-1f, 3.3333331174e-1f);
  y = y * m * z;
  F fe = __builtin_convertvector(e, F);
  y = y + fe * -2.12194440e-4f;
  y = y - 0.5f * z;
  return x == x ? m + y + fe * 0.693359375f : x;
}

// log(1 + x) for x >= 0, accurate for small x (Goldberg's trick on log_v).
inline F log1p_v(F x) {
  F u = x + 1.0f;
  F d = u - 1.0f;
  return d == 0 ? x : log_v(u) * (x / d);
}

inline F tanh_v(F x) {
  // Eigen's rational approximation (ptanh_float), exact to a few ulp over [-7.9, 7.9].
  x = clamp(x, -7.90531110763549805f, 7.90531110763549805f);
  F x2 = x * x;
  F p = horner(x2, -2.76076847742355e-16f, 2.00018790482477e-13f, -8.60467152213735e-11f, 5.12229709037114e-08f,
                    1.48572235717979e-05f, 6.37261928875436e-04f, 4.89352455891786e-03f) * x;
  F q = horner(x2, 1.19825839466702e-06f, 1.18534705686654e-04f, 2.26843463243900e-03f, 4.89352518554385e-03f);
  return vabs(x) < 0.0004f ? x : p / q;
}

// sin and cos (Cephes sinf/cosf: reduction by pi/4 in three parts, then the octant's polynomial).
inline void sincos_v(F x0, F* s, F* c) {
  F x = x0;
  F sign_s = x < 0 ? splat<F>(-1.0f) : splat<F>(1.0f);
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
  F sign_c = (((j - 2) & 4) != 0) ? splat<F>(1.0f) : splat<F>(-1.0f);
  *s = sv * sign_s;
  *c = cv * sign_c;
  // Beyond 8192 the three-part reduction loses digits: those lanes (and NaN) go to the C library.
  const auto far = !(vabs(x0) < 8192.0f);
  if (lane_any(far))
    for (int l = 0; l < 8; l++)
      if (far[l]) {
        (*s)[l] = std::sin(x0[l]);
        (*c)[l] = std::cos(x0[l]);
      }
}

#endif  // DK_CPU

// ------------------------------------------------------------------------------------------------
// The counter-based random numbers of drone_torchrl/envs/rng.py (SplitMix64's finaliser on
// (seed, counter, stream, index)): the same 64-bit integers, so the same uniforms exactly;
// the normals' Box-Muller arithmetic (log, cos, sin) agrees with PyTorch's to a few ulp.

constexpr uint64_t kGolden = 0x9E3779B97F4A7C15ull, kMix1 = 0xBF58476D1CE4E5B9ull, kMix2 = 0x94D049BB133111EBull;
constexpr uint64_t kUpdate = 0xD1B54A32D192ED03ull, kStream = 0xAEF17502108EF2D9ull;
// rng.START_STATES, rng.ACTION_NOISE, rng.EPISODE_KEYS; disturbances.EPISODE_STREAM, STEP_STREAM.
constexpr uint64_t kStartStates = 1, kActionNoise = 2, kEpisodeKeys = 3, kEpisodeStream = 11, kStepStream = 12;
constexpr int kUniformBits = 24;

DK_HD inline uint64_t mix(uint64_t x) {
  x = (x ^ (x >> 30)) * kMix1;
  x = (x ^ (x >> 27)) * kMix2;
  return x ^ (x >> 31);
}

// The stream of (seed, counter, stream), from mix(seed) (which an episode's draws compute once).
DK_HD inline uint64_t mixed_stream_key(uint64_t mixed_seed, uint64_t counter, uint64_t stream) {
  return mix(mixed_seed ^ (counter * kUpdate + stream * kStream));
}

DK_HD inline uint64_t stream_key(uint64_t seed, uint64_t counter, uint64_t stream) {
  return mixed_stream_key(mix(seed), counter, stream);
}

// rng.uniform's element `index` of the stream `key`: in (0, 1), exact in float32.
DK_HD inline float uniform(uint64_t key, uint64_t index) {
  const uint64_t top = mix(key + index * kGolden) >> (64 - kUniformBits);
  return (static_cast<float>(top) + 0.5f) / static_cast<float>(1u << kUniformBits);
}

// rng.keys(seed, counter, EPISODE_KEYS, (E,)) element `episode`: an episode's disturbance key.
DK_HD inline uint64_t episode_key(uint64_t seed, uint64_t counter, uint64_t episode) {
  return mix(stream_key(seed, counter, kEpisodeKeys) + episode * kGolden);
}

// Box-Muller in V's precision: (r cos(2 pi u2), r sin(2 pi u2)), r = sqrt(-2 log u1).
template <class V>
DK_HD inline void box_muller(V u1, V u2, V* c, V* s) {
  using S = ScalarOf<V>;
  const V radius = sqrt_v(S(-2) * log_v(u1));
  sincos_v(S(6.28318530717958647692) * u2, s, c);
  *c = radius * *c;
  *s = radius * *s;
}

// rng.normal(seed, counter, ACTION_NOISE, (T, E, 2))'s pair `pair[l]` (t * E + episode) of each
// lane's stream noise_key[l]: the two motors' standard normals, in float32 as PyTorch draws them.
template <class V>
DK_HD inline void action_normals(const uint64_t* noise_key, const uint64_t* pair, V* z) {
  using FV = FloatOf<V>;
  FV u1 = splat<FV>(0.5f), u2 = splat<FV>(0.5f);
  for (int l = 0; l < lanes_of<V>(); l++) {
    set_lane(u1, l, uniform(noise_key[l], 2 * pair[l]));
    set_lane(u2, l, uniform(noise_key[l], 2 * pair[l] + 1));
  }
  FV z0, z1;
  box_muller(u1, u2, &z0, &z1);
  for (int l = 0; l < lanes_of<V>(); l++) {
    set_lane(z[0], l, lane(z0, l));
    set_lane(z[1], l, lane(z1, l));
  }
}

// ------------------------------------------------------------------------------------------------
// The network.

enum Activation { kTanh = 0, kRelu = 1, kElu = 2 };

struct Net {
  int in_dim;
  int n_hidden;
  int activation;
  double min_std;
  // Added to the mean and to the std (ThreeNetPolicy's distribution_eps): Normal(mu + eps, sigma + eps).
  double dist_eps;
  // Where each layer's weight [out, in] starts in the flat vector (its bias follows it): the hidden
  // layers, then the mean head, then the std head. And each layer's input width.
  int offset[kMaxLayers + 2];
  int width[kMaxLayers + 2];
  int params;
  int activations;           // hidden outputs of one row
  int act_offset[kMaxLayers];  // where each hidden layer's outputs start in them

  DK_HD int last() const { return width[n_hidden]; }
  DK_HD int out(int l) const { return l < n_hidden ? width[l + 1] : kActionDim; }  // layer l's outputs
};

template <class V>
DK_HD inline V activate(V x, int activation) {
  if (activation == kTanh) return tanh_v(x);
  if (activation == kRelu) return select(x < 0, V{}, x);
  return select(x > 0, x, exp_v(x) - 1);  // elu, alpha 1
}

// The derivative of the activation from its output y.
template <class V>
DK_HD inline V activation_grad(V y, int activation) {
  if (activation == kTanh) return 1 - y * y;
  if (activation == kRelu) return select(y > 0, V{} + 1, V{});
  return select(y > 0, V{} + 1, y + 1);
}

// torch.nn.functional.softplus (beta 1, threshold 20).
template <class V>
DK_HD inline V softplus(V x) {
  return select(x > 20, x, log1p_v(exp_v(x)));
}

// out[o] = bias[o] + sum_i w[o * row + i * col] * x[i] for o < n, summed in order of i (bias null:
// 0): W x + b with (row, col) = (in, 1), the transposed product W^T d with (1, W's width). Eight
// outputs at a time: eight independent accumulator chains keep the FMA units busy (one chain per
// output would wait on each FMA's latency). W is V (each lane its own agent's weights) or its
// scalar (every lane the same agent); per lane the arithmetic is the same.
template <class V, class W>
DK_HD inline void matvec(const W* w, int row, int col, const W* bias, const V* x, int in, int n, V* out) {
  constexpr int kTile = 8;
  int o = 0;
  for (; o + kTile <= n; o += kTile) {
    V acc[kTile];
    for (int k = 0; k < kTile; k++) acc[k] = bias ? V{} + bias[o + k] : V{};
    for (int i = 0; i < in; i++) {
      const V xi = x[i];
      for (int k = 0; k < kTile; k++) acc[k] += w[(o + k) * row + i * col] * xi;
    }
    for (int k = 0; k < kTile; k++) out[o + k] = acc[k];
  }
  for (; o < n; o++) {
    V acc = bias ? V{} + bias[o] : V{};
    for (int i = 0; i < in; i++) acc += w[o * row + i * col] * x[i];
    out[o] = acc;
  }
}

// out[i] = sum_o w[o * in + i] * d[o] for i < in: the backward's product with the weights [n, in].
template <class V, class W>
DK_HD inline void matvec_t(const W* w, const V* d, int n, int in, V* out) {
  matvec(w, 1, in, static_cast<const W*>(nullptr), d, n, in, out);
}

// The forward pass from inputs x: the hidden outputs (acts, layer after layer), loc, and the std
// head's pre-activation.
template <class V, class W>
DK_HD inline void forward(const Net& net, const W* w, const V* x, V* acts, V* loc, V* pre_std) {
  const V* input = x;
  V* out = acts;
  for (int l = 0; l < net.n_hidden; l++) {
    const int n = net.out(l), in = net.width[l];
    matvec(w + net.offset[l], in, 1, w + net.offset[l] + n * in, input, in, n, out);
    for (int o = 0; o < n; o++) out[o] = activate(out[o], net.activation);
    input = out;
    out += n;
  }
  const int in = net.last();
  for (int head = 0; head < 2; head++) {
    const W* hw = w + net.offset[net.n_hidden + head];
    matvec(hw, in, 1, hw + kActionDim * in, input, in, kActionDim, head == 0 ? loc : pre_std);
  }
}

// The backward of one step, first pass: the gradient of every hidden layer's pre-activation
// (deltas, layer after layer like acts) from d_loc and d_pre (the std head's pre-activation).
template <class V, class W>
DK_HD inline void backward_deltas(const Net& net, const W* w, const V* acts, const V* d_loc, const V* d_pre,
                                  V* deltas) {
  if (net.n_hidden == 0) return;
  const int* act_offset = net.act_offset;
  // d(last hidden output) = Wm^T d_loc + Ws^T d_pre, then through the activation.
  const int top = net.n_hidden - 1, n_top = net.out(top);
  const W* wm = w + net.offset[net.n_hidden];
  const W* ws = w + net.offset[net.n_hidden + 1];
  V* d = deltas + act_offset[top];
  V from_std[kMaxWidth];
  matvec_t(wm, d_loc, kActionDim, n_top, d);
  matvec_t(ws, d_pre, kActionDim, n_top, from_std);
  for (int i = 0; i < n_top; i++)
    d[i] = (d[i] + from_std[i]) * activation_grad(acts[act_offset[top] + i], net.activation);
  for (int l = top; l > 0; l--) {
    const int n = net.out(l), n_in = net.width[l];
    const W* wl = w + net.offset[l];
    const V* dl = deltas + act_offset[l];
    V* below = deltas + act_offset[l - 1];
    matvec_t(wl, dl, n, n_in, below);
    for (int i = 0; i < n_in; i++) below[i] *= activation_grad(acts[act_offset[l - 1] + i], net.activation);
  }
}

// The backward's second pass for one layer: grad_w[o, i] += sum over steps of d[o] * in[i] (per lane),
// grad_b[o] += sum of d[o], over `steps` steps whose vectors are `d_stride` and `in_stride` apart.
// Four by four outputs and inputs at a time, so each loaded vector feeds four FMAs.
template <class V>
DK_HD inline void weight_grad(const V* d, int d_stride, const V* in, int in_stride, int n, int n_in, int64_t steps,
                              V* grad_w, V* grad_b) {
  constexpr int kTile = 4;
  for (int o0 = 0; o0 < n; o0 += kTile) {
    const int no = n - o0 < kTile ? n - o0 : kTile;
    for (int i0 = 0; i0 < n_in; i0 += kTile) {
      const int ni = n_in - i0 < kTile ? n_in - i0 : kTile;
      V acc[kTile][kTile] = {};
      for (int64_t b = 0; b < steps; b++) {
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
      for (int64_t b = 0; b < steps; b++) acc += d[b * d_stride + o0 + a];
      grad_b[o0 + a] += acc;
    }
  }
}

// ------------------------------------------------------------------------------------------------
// The drone (envs/dynamics.py; eqs. 2.1-2.3 of the paper, semi-implicit Euler) and its
// disturbances (envs/disturbances.py).

// The env constants and the disturbance's magnitudes, in the order drone_torchrl/kernels/ops.py
// packs them (build.ENV_CONSTANTS: DroneParams' fields, bounds as 1 for strict and max_thrust < 0 for
// unbounded, then the values derived from them and the rest; ops.DISTURBANCE_CONSTANTS:
// disturbances.FIELDS). One list each: the enums below and the names dk_env_constants() and
// dk_disturbance_constants() give, which the loader (build.py) compares with Python's.
#define DK_ENV_CONSTANTS(X)                                                                                  \
  X(mass) X(motor_distance) X(gravity) X(dt) X(max_thrust) X(floor_tolerance) X(x_limit) X(z_min) X(z_max)   \
  X(alpha_limit) X(zone_x_limit) X(zone_z_min) X(zone_z_max) X(bounds) X(weight) X(arm_over_inertia) X(floor) \
  X(zone_z_centre) X(reward_zone) X(reward_alive) X(reward_terminated) X(reset_noise) X(squash_high)        \
  X(reset_air)
#define DK_DISTURBANCE_CONSTANTS(X)                                                                          \
  X(wind) X(gust) X(gust_time) X(mass) X(motor_gain) X(motor_lag) X(noise_position) X(noise_angle)           \
  X(action_delay) X(observed_actions)
#define DK_ENV_ENUM(name) env_##name,
#define DK_DIST_ENUM(name) dist_##name,
#define DK_NAME(name) #name ","
enum EnvConst { DK_ENV_CONSTANTS(DK_ENV_ENUM) kEnvConsts };
enum DistConst { DK_DISTURBANCE_CONSTANTS(DK_DIST_ENUM) kDistConsts };

// What the policy sees of a drone observing its last `observed` commands: the state, then the
// commands newest first (disturbances.observation_names; the loader compares the widths).
DK_HD constexpr int observation_dim(int observed) { return kStateDim + observed * kActionDim; }

// TerminationCause codes.
constexpr int kOutX = 1, kFloorHit = 2, kCeiling = 3, kTilt = 4;
constexpr double kHover = 0.5;  // dynamics.HOVER_THRUST
constexpr int kEpisodeUniforms = 4;  // disturbances._EPISODE_UNIFORMS: wind, mass, two gains

// The env constants in S, each named as in DK_ENV_CONSTANTS, and what the kernels derive from them.
#define DK_ENV_FIELD(name) S name;
#define DK_ENV_READ(name) e.name = env[env_##name];
template <class S>
struct EnvParams {
  DK_ENV_CONSTANTS(DK_ENV_FIELD)
  S half, log_half, squash_lim, min_std, dist_eps;
  bool bounded, strict;
};

template <class S>
DK_HD inline EnvParams<S> env_params(const double* env, const Net& net) {
  EnvParams<S> e;
  DK_ENV_CONSTANTS(DK_ENV_READ)
  e.half = env[env_squash_high] / 2, e.log_half = e.squash_high > 0 ? std::log(e.half) : 0;
  e.squash_lim = S(1) - (sizeof(S) == 4 ? S(1e-6) : S(1e-15));  // TorchRL's safe tanh and atanh
  e.min_std = net.min_std, e.dist_eps = net.dist_eps;
  e.bounded = env[env_max_thrust] >= 0, e.strict = env[env_bounds] > 0;
  return e;
}

// The disturbances' magnitudes and the per-step coefficients they imply (Python's float64 arithmetic).
template <class S>
struct DistParams {
  bool nominal;  // the paper's drone: nothing drawn, carried or observed beyond the state
  bool gusty, noisy, lagged;
  int delay, observed;
  S wind, gust, mass, motor_gain, noise_position, noise_angle, gust_decay, gust_scale, lag;
};

template <class S>
DK_HD inline DistParams<S> dist_params(const double* c, double dt) {
  DistParams<S> d{};
  d.nominal = true;
  if (c == nullptr) return d;
  for (int k = 0; k < kDistConsts; k++) d.nominal = d.nominal && (k == dist_gust_time || c[k] == 0);
  d.wind = c[dist_wind], d.gust = c[dist_gust], d.mass = c[dist_mass], d.motor_gain = c[dist_motor_gain];
  d.noise_position = c[dist_noise_position], d.noise_angle = c[dist_noise_angle];
  d.gusty = c[dist_gust] != 0, d.noisy = c[dist_noise_position] != 0 || c[dist_noise_angle] != 0;
  d.lagged = c[dist_motor_lag] != 0;
  d.delay = static_cast<int>(c[dist_action_delay]), d.observed = static_cast<int>(c[dist_observed_actions]);
  const double decay = d.gusty ? std::exp(-dt / c[dist_gust_time]) : 0.0;
  d.gust_decay = decay;
  d.gust_scale = c[dist_gust] * std::sqrt(1.0 - decay * decay);
  d.lag = d.lagged ? 1.0 - std::exp(-dt / c[dist_motor_lag]) : 0.0;
  return d;
}

// One drone per lane: its physical state, its episode's draws and what a disturbed drone carries
// (disturbances.EpisodeDraw and Internal).
template <class V>
struct Drone {
  V s[kStateDim];
  V wind, mass_ratio, gain[kActionDim];
  V gust, thrust[kActionDim];
  V pending[kMaxBack][kActionDim];  // commands issued, not yet acting, oldest first
  V issued[kMaxBack][kActionDim];   // the last commands issued, newest first
  uint64_t key[lanes_of<V>()];      // each lane's episode key
  uint64_t mixed[lanes_of<V>()];    // mix(key): the first half of every stream key of the episode
};

// dynamics.states_from_uniform of the uniforms of stream start_key's row `episode` (component k):
// the jitter in float32, then the start point (the zone's centre or the floor) in S.
template <class S>
DK_HD inline S start_component(const double* env, uint64_t start_key, uint64_t episode, int k) {
  const bool air = env[env_reset_air] > 0;
  const float u = uniform(start_key, episode * kStateDim + k);
  const float jitter = (2.0f * u - 1.0f) * static_cast<float>(env[env_reset_noise]);
  const bool kept = air || k == 0 || k == 4;  // floor: x and alpha only
  const S base = k != 2 ? S(0) : air ? S(env[env_zone_z_centre]) : S(env[env_z_min]);
  return (kept ? S(jitter) : S(0)) + base;
}

// disturbances.draw_episode and disturbances.start: the episode's draws and initial internal state
// of each lane (of those `only` names, when given) from its key (dr.key). The physical state is
// left alone.
template <class V>
DK_HD inline void start_episode(const DistParams<ScalarOf<V>>& d, Drone<V>& dr, const bool* only = nullptr) {
  using S = ScalarOf<V>;
  V u[kEpisodeUniforms + 2] = {}, chosen{};
  for (int l = 0; l < lanes_of<V>(); l++) {
    if (only && !only[l]) continue;
    set_lane(chosen, l, S(1));
    dr.mixed[l] = mix(dr.key[l]);
    const uint64_t k = mixed_stream_key(dr.mixed[l], 0, kEpisodeStream);
    for (int i = 0; i < kEpisodeUniforms + 2; i++) set_lane(u[i], l, S(uniform(k, i)));
  }
  const auto on = chosen != S(0);
  V spread[kEpisodeUniforms];
  for (int i = 0; i < kEpisodeUniforms; i++) spread[i] = S(2) * u[i] - S(1);
  dr.wind = select(on, d.wind * spread[0], dr.wind);
  dr.mass_ratio = select(on, S(1) + d.mass * spread[1], dr.mass_ratio);
  for (int m = 0; m < kActionDim; m++) dr.gain[m] = select(on, S(1) + d.motor_gain * spread[2 + m], dr.gain[m]);
  V first, second;  // the normal pair of uniforms 4 and 5: the stationary law's first gust
  box_muller(u[kEpisodeUniforms], u[kEpisodeUniforms + 1], &first, &second);
  dr.gust = select(on, d.gust * first, dr.gust);
  for (int m = 0; m < kActionDim; m++) {
    dr.thrust[m] = select(on, splat<V>(S(kHover)), dr.thrust[m]);
    for (int j = 0; j < d.delay; j++) dr.pending[j][m] = select(on, splat<V>(S(kHover)), dr.pending[j][m]);
    for (int j = 0; j < d.observed; j++) dr.issued[j][m] = select(on, V{}, dr.issued[j][m]);
  }
}

// What a drone carries from one segments call to the next besides its state and key
// (disturbances.Internal): fn(k, i, value) for each value, i its place in row r of carried tensor k
// (RolloutArgs' internal: gust, thrust, pending, issued).
template <class V, class Fn>
DK_HD inline void each_internal(const DistParams<ScalarOf<V>>& d, Drone<V>& dr, int64_t r, Fn fn) {
  fn(0, r, dr.gust);
  for (int m = 0; m < kActionDim; m++) {
    fn(1, r * kActionDim + m, dr.thrust[m]);
    for (int j = 0; j < d.delay; j++) fn(2, (r * d.delay + j) * kActionDim + m, dr.pending[j][m]);
    for (int j = 0; j < d.observed; j++) fn(3, (r * d.observed + j) * kActionDim + m, dr.issued[j][m]);
  }
}

// disturbances._normal(key, t, STEP_STREAM, 4) of each lane (t[l] its episode's step): n[0] the
// gust's innovation, n[1..3] the noise on x, z and alpha. Only the pairs in use are drawn.
template <class V>
DK_HD inline void step_normals(const DistParams<ScalarOf<V>>& d, const Drone<V>& dr, const int64_t* t, V* n) {
  using S = ScalarOf<V>;
  const int pairs = d.noisy ? 2 : d.gusty ? 1 : 0;
  if (pairs == 0) return;
  V u[4];
  for (int l = 0; l < lanes_of<V>(); l++) {
    const uint64_t k = mixed_stream_key(dr.mixed[l], static_cast<uint64_t>(t[l]), kStepStream);
    for (int i = 0; i < 2 * pairs; i++) set_lane(u[i], l, S(uniform(k, i)));
  }
  for (int p = 0; p < pairs; p++) box_muller(u[2 * p], u[2 * p + 1], &n[2 * p], &n[2 * p + 1]);
}

// disturbances.observe: what the policy sees (in_dim values) of the state, with n the step's normals.
template <class V>
DK_HD inline void observe(const DistParams<ScalarOf<V>>& d, const Drone<V>& dr, const V* n, V* obs) {
  for (int k = 0; k < kStateDim; k++) obs[k] = dr.s[k];
  if (d.noisy) {
    obs[0] = dr.s[0] + d.noise_position * n[1];
    obs[2] = dr.s[2] + d.noise_position * n[2];
    obs[4] = dr.s[4] + d.noise_angle * n[3];
  }
  for (int j = 0; j < d.observed; j++)
    for (int m = 0; m < kActionDim; m++) obs[kStateDim + j * kActionDim + m] = dr.issued[j][m];
}

// The policy at inputs x: hidden outputs (acts), loc (shifted by dist_eps), the std head's
// pre-activation, and the action f(loc + scale * z) (z null: the deterministic f(loc)), where f is
// the identity (Normal head) or TorchRL's TanhNormal squash onto [0, high].
template <class V, class W>
DK_HD inline void policy_step(const Net& net, const EnvParams<ScalarOf<V>>& e, const W* w, const V* x, V* acts,
                              const V* z, V* loc, V* pre, V* act) {
  forward(net, w, x, acts, loc, pre);
  for (int m = 0; m < kActionDim; m++) {
    if (e.dist_eps != 0) loc[m] = loc[m] + e.dist_eps;
    V u = loc[m];
    if (z) u = loc[m] + (softplus(pre[m]) + e.min_std + e.dist_eps) * z[m];
    if (e.squash_high > 0) u = e.half + e.half * clamp(tanh_v(u), -e.squash_lim, e.squash_lim);
    act[m] = u;
  }
}

// dynamics.termination_cause: a beyond b is a > b, or a >= b with strict bounds (a value beyond an
// upper bound, or a lower bound beyond the value). dynamics.in_target_zone: a within b is a <= b, or
// a < b strict. (Each written out: a negated comparison would count NaN as inside the zone.)
template <class A, class B>
DK_HD inline auto beyond(bool strict, A a, B b) {
  return strict ? a >= b : a > b;
}
template <class A, class B>
DK_HD inline auto within(bool strict, A a, B b) {
  return strict ? a < b : a <= b;
}

// The termination cause (a TerminationCause code as a number), the reward and whether the state
// is in the target zone (1 or 0), of the state n after a step (dynamics.termination_cause, reward).
template <class V>
DK_HD inline void judge(const EnvParams<ScalarOf<V>>& e, const V* n, V* reward, V* cause, V* zone) {
  using S = ScalarOf<V>;
  const bool st = e.strict;
  const V ax = vabs(n[0]), aa = vabs(n[4]);
  // The lowest non-zero code wins: assign from the highest down.
  V c = select(beyond(st, aa, e.alpha_limit), splat<V>(S(kTilt)), V{});
  c = select(beyond(st, n[2], e.z_max), splat<V>(S(kCeiling)), c);
  c = select(beyond(st, e.floor, n[2]), splat<V>(S(kFloorHit)), c);
  c = select(beyond(st, ax, e.x_limit), splat<V>(S(kOutX)), c);
  const auto in = both(both(within(st, ax, e.zone_x_limit), within(st, e.zone_z_min, n[2])),
                       both(within(st, n[2], e.zone_z_max), within(st, aa, e.alpha_limit)));
  *reward = select(c != S(0), splat<V>(e.reward_terminated),
                   select(in, splat<V>(e.reward_zone), splat<V>(e.reward_alive)));
  *cause = c;
  *zone = select(in, splat<V>(S(1)), V{});
}

// The semi-implicit Euler step: velocities first, then positions with the new velocities.
template <class V>
DK_HD inline void euler(const V* s, V x_ddot, V z_ddot, V alpha_ddot, ScalarOf<V> dt, V* n) {
  n[1] = s[1] + x_ddot * dt;
  n[3] = s[3] + z_ddot * dt;
  n[5] = s[5] + alpha_ddot * dt;
  n[0] = s[0] + n[1] * dt;
  n[2] = s[2] + n[3] * dt;
  n[4] = s[4] + n[5] * dt;
}

// One step of each lane's drone from dr.s under the commands act just issued: disturbances.step
// (dynamics.step for the nominal drone): the next state, reward, cause and zone (judge), and the
// drone's internal state advanced (dr.s is left for the caller). gust_n: the step's gust normal.
template <class V>
DK_HD inline void drone_step(const EnvParams<ScalarOf<V>>& e, const DistParams<ScalarOf<V>>& d, Drone<V>& dr,
                             const V* act, V gust_n, V* next, V* reward, V* cause, V* zone) {
  using S = ScalarOf<V>;
  V sin_a, cos_a;
  if (d.nominal) {
    V a_l = act[0], a_r = act[1];
    if (e.bounded) {
      a_l = clamp(a_l, S(0), e.max_thrust);
      a_r = clamp(a_r, S(0), e.max_thrust);
    }
    // In this order (the compiler's fused multiply-adds follow it): nominal episodes bit for bit
    // those of the kernels before disturbances.
    const V thrust_l = a_l * e.weight, thrust_r = a_r * e.weight, total = thrust_l + thrust_r;
    sincos_v(dr.s[4], &sin_a, &cos_a);
    const V x_ddot = -sin_a * total / e.mass;
    const V z_ddot = cos_a * total / e.mass - e.gravity;
    const V alpha_ddot = (thrust_r - thrust_l) * e.arm_over_inertia;
    euler(dr.s, x_ddot, z_ddot, alpha_ddot, e.dt, next);
  } else {
    for (int j = d.observed - 1; j > 0; j--)
      for (int m = 0; m < kActionDim; m++) dr.issued[j][m] = dr.issued[j - 1][m];
    V command[kActionDim];
    for (int m = 0; m < kActionDim; m++) {
      if (d.observed > 0) dr.issued[0][m] = act[m];
      command[m] = act[m];
      if (d.delay > 0) {
        command[m] = dr.pending[0][m];
        for (int j = 0; j + 1 < d.delay; j++) dr.pending[j][m] = dr.pending[j + 1][m];
        dr.pending[d.delay - 1][m] = act[m];
      }
      if (e.bounded) command[m] = clamp(command[m], S(0), e.max_thrust);
      // With a lag the motors' thrust follows the command; without, it is the command.
      dr.thrust[m] = d.lagged ? dr.thrust[m] + d.lag * (command[m] - dr.thrust[m]) : command[m];
    }
    const V a_l = dr.thrust[0] * dr.gain[0], a_r = dr.thrust[1] * dr.gain[1], total = a_l + a_r;
    sincos_v(dr.s[4], &sin_a, &cos_a);
    const V force = dr.wind + dr.gust;
    // x'' = g (sin(-alpha) total + force) / ratio, z'' = g cos(alpha) total / ratio - g,
    // alpha'' = (a_r - a_l) m0 g r / (I0 ratio) (the inertia follows the mass).
    euler(dr.s, e.gravity * (-sin_a * total + force) / dr.mass_ratio,
          e.gravity * cos_a * total / dr.mass_ratio - e.gravity,
          (a_r - a_l) * e.weight * e.arm_over_inertia / dr.mass_ratio, e.dt, next);
    if (d.gusty) dr.gust = dr.gust * d.gust_decay + d.gust_scale * gust_n;
  }
  judge(e, next, reward, cause, zone);
}

// The log-probability log pi(action) of the stored actions under Normal(loc, scale) (or TorchRL's
// TanhNormal: the sample the action came from, as TorchRL inverts it, and the squash's log-det),
// summed over the motors, and coef times its derivatives in loc and in the std head's
// pre-activation (the REINFORCE loss' backward into the heads). scale: the policy's std.
template <class V>
DK_HD inline V log_prob_backward(const EnvParams<ScalarOf<V>>& e, const V* loc, const V* pre, const V* action,
                                 V coef, V* d_loc, V* d_pre, V* scale) {
  using S = ScalarOf<V>;
  const S half_log_2pi = S(0.91893853320467274178);  // log(sqrt(2 pi))
  V log_prob{};
  for (int m = 0; m < kActionDim; m++) {
    scale[m] = softplus(pre[m]) + e.min_std + e.dist_eps;
    V sample = action[m];
    if (e.squash_high > 0) {
      const V y = clamp((action[m] - e.half) / e.half, -e.squash_lim, e.squash_lim);
      sample = S(0.5) * (log1p_v(y) - log1p_v(-y));  // atanh
      // log |d action / d sample| of the tanh and the affine map (TanhTransform's formula).
      log_prob -= S(2) * (S(0.69314718055994530942) - sample - softplus(S(-2) * sample)) + e.log_half;
    }
    const V z = (sample - loc[m]) / scale[m];
    log_prob += S(-0.5) * z * z - log_v(scale[m]) - half_log_2pi;
    d_loc[m] = coef * z / scale[m];
    const V d_scale = coef * (z * z - S(1)) / scale[m];
    const V ex = exp_v(pre[m]);  // softplus' (beta 1, threshold 20): sigmoid below the threshold
    d_pre[m] = select(pre[m] > S(20), d_scale, d_scale * ex / (ex + S(1)));
  }
  return log_prob;
}

// ------------------------------------------------------------------------------------------------
// The engine's loops, single source as well: fly_block (a block of rows: whole episodes, or
// PPO/A2C's auto-resetting segments) and reinforce_agent (one agent's loss and gradient), each on
// lanes<V>() drones at a time and on scratch memory the caller owns. The CPU engine (below) calls
// them with V a vector over threads of blocks; the CUDA build (drone_kernels.cu) with V = Real, one
// thread per row or agent; the scalar engine (-DDK_SCALAR_ENGINE, tested against the CPU engine)
// runs the CUDA threads' code on the CPU.

// One build per precision (build.py compiles float64 only when a run asks for it): the scalar type
// of every tensor the C interface takes.
#ifndef DK_DOUBLE
#define DK_DOUBLE 0
#endif
using Real = std::conditional_t<DK_DOUBLE != 0, double, float>;

// Element i of a tensor of S that the C interface passes untyped.
template <class S>
DK_HD inline S& ref(const void* p, int64_t i) {
  return const_cast<S*>(static_cast<const S*>(p))[i];
}

// What dk_rollout flies: rows = agents * episodes (row r flies agent r / episodes's policy), each
// until its episode terminates or `steps` steps; or, with t (ops.segments: one agent, episodes =
// rows), `steps` steps of each drone, its episode carried in and out and a new one started as soon
// as one ends (DroneEnv under TorchRL's collector). Per step [rows, steps, ...]; null: not written.
// The caller zero-fills the outputs (length and stats count from there).
struct RolloutArgs {
  int64_t rows, episodes, steps;
  const void* params;
  const void* start;   // [rows, 6]; segments: the carried state
  const void* noise;   // null: deterministic (the mean action), unless rng is given
  const int64_t* rng;  // [rows, 2]: the row's agent's seed and update counter; start and noise are then drawn here
  const int64_t* keys;  // [rows]: each episode's disturbance key; null: drawn from rng
  const uint8_t* active;
  const double* env;
  const double* dist;   // the disturbance's magnitudes (DistConst); null: the nominal drone
  const double* gamma;  // [agents]: the discount of each agent's returns-to-go
  void* states;         // [rows, steps + 1, 6]: the true states
  void* action;
  void* reward;
  int64_t* cause;
  int64_t* length;
  void* returns;  // [rows, steps]: sum_{k >= t} gamma^(k - t) reward_k over the row's episode
  double* stats;  // [rows, kStats]
  void* seen;     // [rows, steps, in_dim]: what the policy saw
  // Optional: what the REINFORCE gradient needs of every step, in lane vectors per agent (Saved).
  void* saved;
  // Segments. Carried in: t [rows] (< 0: a new episode starts at step 0; null: no segments) and
  // the internal state: gust [rows], thrust [rows, 2], pending [rows, delay, 2], issued [rows,
  // observed, 2]. A new episode at step j starts from fresh[., j] with key fresh_keys[., j] (null:
  // the nominal drone); one truncates at max_steps.
  int64_t max_steps;
  const int64_t* t;
  const void* internal[4];
  const void* fresh;
  const int64_t* fresh_keys;
  void* next_obs;
  uint8_t* terminated;
  uint8_t* truncated;
  int64_t* step_count;
  // Carried out, laid out as carried in.
  void* state_out;
  int64_t* t_out;
  int64_t* key_out;
  void* internal_out[4];
};

// Where the gradient pass finds each step: an agent's steps r = episode * steps + t go in blocks of
// L lanes (block r / L, lane r % L), each block W vectors: the observation, the hidden outputs,
// loc, the std head's pre-activation, the action and the return-to-go.
struct Saved {
  int in_dim, activations, width;  // width: vectors per block
  int64_t blocks;                  // per agent
  DK_HD int acts() const { return in_dim; }  // after the observation, at 0
  DK_HD int loc() const { return in_dim + activations; }
  DK_HD int pre() const { return loc() + kActionDim; }
  DK_HD int action() const { return pre() + kActionDim; }
  DK_HD int ret() const { return action() + kActionDim; }
  DK_HD static Saved of(const Net& net, int64_t episodes, int64_t steps, int lanes) {
    const int width = net.in_dim + net.activations + 3 * kActionDim + 1;
    return {net.in_dim, net.activations, width, (episodes * steps + lanes - 1) / lanes};
  }
};

// Per-row counts for the episode metrics (drone_torchrl/episodes.py's definitions): the return,
// the steps that ended inside the target zone without terminating, the negative motor commands,
// and the termination cause of the last step.
enum Stat { kReturn, kZoneSteps, kNegative, kLastCause, kStats };

// Rows b * L .. b * L + L - 1 of dk_rollout (L = lanes<V>()). wbuf: scratch of net.params vectors
// (the lanes' weights, where they fly different agents), acts: of max(net.activations, 1), x: of
// net.in_dim.
template <class V>
DK_HD inline void fly_block(const Net& net, const RolloutArgs& a, int64_t b, V* wbuf, V* acts, V* x) {
  using S = ScalarOf<V>;
  constexpr int L = lanes_of<V>();
  const Saved layout = Saved::of(net, a.episodes, a.steps, L);
  // The scalar of vector k of agent n's step r in the saved buffer.
  auto slot = [&](int64_t n, int64_t r, int k) -> S& {
    return ref<S>(a.saved, ((n * layout.blocks + r / L) * layout.width + k) * L + r % L);
  };
  const EnvParams<S> e = env_params<S>(a.env, net);
  const DistParams<S> d = dist_params<S>(a.dist, a.env[env_dt]);
  const S* params = static_cast<const S*>(a.params);
  Drone<V> dr{};
  const int64_t T = a.steps, in_dim = net.in_dim, row0 = b * L;
  const int count = static_cast<int>(row0 + L <= a.rows ? L : a.rows - row0);
  // Each lane's row, its agent and the row's episode index within it, its episode's step, whether
  // it flies on and whether it starts a new episode at the next step.
  int64_t row[L], agent[L], t[L];
  uint64_t episode[L], noise_key[L];
  bool live[L], restart[L], any = false, one = true;
  for (int l = 0; l < L; l++) {
    row[l] = row0 + (l < count ? l : 0);
    agent[l] = row[l] / a.episodes, episode[l] = row[l] % a.episodes;
    live[l] = l < count && a.active[agent[l]];
    any = any || live[l];
    one = one && agent[l] == agent[0];
    t[l] = a.t ? a.t[row[l]] : 0;
    restart[l] = t[l] < 0;
  }
  if (!any) return;
  // One agent's weights are read where they are (every lane the same); else lane l of wbuf[k] is
  // parameter k of agent[l].
  for (int l = 0; l < L && !one; l++)
    for (int k = 0; k < net.params; k++) set_lane(wbuf[k], l, params[agent[l] * net.params + k]);
  for (int l = 0; l < L; l++) {
    if (a.rng) {  // the stream keys of the lane's agent
      const uint64_t seed = a.rng[2 * row[l]], counter = a.rng[2 * row[l] + 1];
      noise_key[l] = stream_key(seed, counter, kActionNoise);
      const uint64_t start_key = stream_key(seed, counter, kStartStates);
      for (int k = 0; k < kStateDim; k++) set_lane(dr.s[k], l, start_component<S>(a.env, start_key, episode[l], k));
      dr.key[l] = a.keys ? a.keys[row[l]] : episode_key(seed, counter, episode[l]);
    } else {
      for (int k = 0; k < kStateDim; k++) set_lane(dr.s[k], l, ref<S>(a.start, row[l] * kStateDim + k));
      dr.key[l] = a.keys ? a.keys[row[l]] : 0;
    }
  }
  if (!d.nominal) {
    start_episode(d, dr);  // the episode's draws; a segment's internal state is the carried one
    for (int l = 0; l < L && a.t; l++)
      each_internal(d, dr, row[l], [&](int k, int64_t i, V& v) { set_lane(v, l, ref<S>(a.internal[k], i)); });
  }
  const bool stochastic = a.noise || a.rng;
  V n[4] = {};
  for (int64_t j = 0; j < T && any; j++) {
    bool restarting = false;
    for (int l = 0; l < L; l++) restarting = restarting || restart[l];
    if (restarting) {  // new episodes from step j: start state fresh[., j], key fresh_keys[., j]
      for (int l = 0; l < L; l++) {
        if (!restart[l]) continue;
        t[l] = 0;
        for (int k = 0; k < kStateDim; k++) set_lane(dr.s[k], l, ref<S>(a.fresh, (row[l] * T + j) * kStateDim + k));
        if (a.fresh_keys) dr.key[l] = a.fresh_keys[row[l] * T + j];
      }
      if (!d.nominal) start_episode(d, dr, restart);
      for (int l = 0; l < L; l++) restart[l] = false;
    }
    if (j == 0 || restarting) {  // else x holds the last step's next observation
      step_normals(d, dr, t, n);
      observe(d, dr, n, x);
    }
    V z[kActionDim]{}, loc[kActionDim], pre[kActionDim], act[kActionDim];
    if (a.rng) {
      uint64_t pair[L];
      for (int l = 0; l < L; l++) pair[l] = static_cast<uint64_t>(j) * a.episodes + episode[l];
      action_normals(noise_key, pair, z);
    } else if (a.noise) {
      for (int m = 0; m < kActionDim; m++)
        for (int l = 0; l < L; l++)
          set_lane(z[m], l, live[l] ? ref<S>(a.noise, (row[l] * T + j) * kActionDim + m) : S(0));
    }
    V* const noisy = stochastic ? z : nullptr;
    if (one) policy_step(net, e, params + agent[0] * net.params, x, acts, noisy, loc, pre, act);
    else policy_step(net, e, static_cast<const V*>(wbuf), x, acts, noisy, loc, pre, act);
    V next[kStateDim], r, cause, zone;
    drone_step(e, d, dr, act, n[0], next, &r, &cause, &zone);
    for (int l = 0; l < count; l++) {
      if (!live[l]) continue;
      const int64_t at = row[l] * T + j, state_at = row[l] * (T + 1) + j;
      const int64_t code = static_cast<int64_t>(lane(cause, l));
      if (a.states) {
        for (int k = 0; k < kStateDim; k++) {
          ref<S>(a.states, state_at * kStateDim + k) = lane(dr.s[k], l);
          ref<S>(a.states, (state_at + 1) * kStateDim + k) = lane(next[k], l);
        }
      }
      if (a.seen)
        for (int k = 0; k < in_dim; k++) ref<S>(a.seen, at * in_dim + k) = lane(x[k], l);
      if (a.action)
        for (int m = 0; m < kActionDim; m++) ref<S>(a.action, at * kActionDim + m) = lane(act[m], l);
      if (a.saved) {
        const int64_t r_agent = episode[l] * T + j;
        for (int k = 0; k < in_dim; k++) slot(agent[l], r_agent, k) = lane(x[k], l);
        for (int k = 0; k < net.activations; k++) slot(agent[l], r_agent, layout.acts() + k) = lane(acts[k], l);
        for (int m = 0; m < kActionDim; m++) {
          slot(agent[l], r_agent, layout.loc() + m) = lane(loc[m], l);
          slot(agent[l], r_agent, layout.pre() + m) = lane(pre[m], l);
          slot(agent[l], r_agent, layout.action() + m) = lane(act[m], l);
        }
      }
      if (a.step_count) a.step_count[at] = t[l];
      ref<S>(a.reward, at) = lane(r, l);
      a.cause[at] = code;
      if (a.length) a.length[row[l]] = j + 1;
      if (a.stats) {
        double* stat = a.stats + row[l] * kStats;
        stat[kReturn] += lane(r, l);
        stat[kZoneSteps] += lane(zone, l) != 0 && code == 0;
        stat[kNegative] += (lane(act[0], l) < 0) + (lane(act[1], l) < 0);
        stat[kLastCause] = code;
      }
    }
    for (int k = 0; k < kStateDim; k++) dr.s[k] = next[k];
    for (int l = 0; l < L; l++) t[l] += 1;
    // What the env returns: the observation of the state after the step, at its step count.
    step_normals(d, dr, t, n);
    observe(d, dr, n, x);
    any = false;
    for (int l = 0; l < count; l++) {
      if (!live[l]) continue;
      const int64_t at = row[l] * T + j, code = static_cast<int64_t>(lane(cause, l));
      if (a.t) {  // a segment's drone flies on: a new episode at the next step once this one ends
        restart[l] = code != 0 || t[l] >= a.max_steps;
        a.terminated[at] = code != 0;
        a.truncated[at] = code == 0 && restart[l];
        for (int k = 0; k < in_dim; k++) ref<S>(a.next_obs, at * in_dim + k) = lane(x[k], l);
      } else {
        live[l] = code == 0;
      }
      any = any || live[l];
    }
  }
  for (int l = 0; l < count; l++) {
    const int64_t r = row[l];
    if (a.returns) {  // returns-to-go of the row's episode, last step first (the loss's discounted_returns)
      const S discount = a.gamma[agent[l]];
      S running = 0;
      for (int64_t j = a.length[r] - 1; j >= 0; j--) {
        running = ref<S>(a.reward, r * T + j) + discount * running;
        ref<S>(a.returns, r * T + j) = running;
        if (a.saved) slot(agent[l], episode[l] * T + j, layout.ret()) = running;
      }
    }
    if (!a.t) continue;
    // What a segment's drone carries out. The nominal drone carries nothing: its gust 0 and its
    // thrust the hover command, as at a start.
    for (int k = 0; k < kStateDim; k++) ref<S>(a.state_out, r * kStateDim + k) = lane(dr.s[k], l);
    a.t_out[r] = restart[l] ? -1 : t[l];
    a.key_out[r] = static_cast<int64_t>(dr.key[l]);
    each_internal(d, dr, r, [&](int k, int64_t i, V& v) {
      ref<S>(a.internal_out[k], i) = d.nominal ? S(k == 1 ? kHover : 0) : lane(v, l);
    });
  }
}

// The loss options of drone_torchrl/objectives/reinforce.py (reinforce_terms), in this order.
struct LossOptions {
  int64_t baseline_mean, normalize_returns, discount_weight, mean_log_prob;
};

struct GradArgs {
  RolloutArgs roll;  // rows = agents * episodes
  int64_t agents;
  LossOptions options;
  // The caller fills these with zeros (actions_finite: ones), what an inactive agent gets.
  void* grad;               // [agents, params]
  double* loss;             // [agents]: each agent's REINFORCE loss (reinforce_terms' loss_per_agent)
  double* std_mean;         // [agents]: the policy's mean std over the valid steps and motors
  uint8_t* actions_finite;  // [agents]
};

// The REINFORCE loss of each agent (ReinforceLoss: -sum_t w_t log pi(a_t | o_t) over its valid
// steps, divided by its episodes) and its gradient, from the steps the rollout saved: the
// log-probability's derivatives in loc and scale (log_prob_backward), then the network's backward
// through the saved hidden outputs (backward_deltas per block, weight_grad over the blocks). No
// forward pass again.
// Agent n's. Scratch: deltas of blocks * max(net.activations, 1) vectors, heads of blocks * 4,
// grad of net.params (blocks: Saved::of's).
template <class V>
DK_HD inline void reinforce_agent(const Net& net, const GradArgs& g, int64_t n, V* deltas, V* heads, V* grad) {
  using S = ScalarOf<V>;
  constexpr int L = lanes_of<V>();
  const RolloutArgs& a = g.roll;
  const LossOptions& o = g.options;
  const int64_t E = a.episodes, T = a.steps;
  const Saved layout = Saved::of(net, E, T, L);
  const EnvParams<S> env = env_params<S>(a.env, net);
  const int p = net.params, act_w = net.activations > 0 ? net.activations : 1;
  const S eps = sizeof(S) == 4 ? S(1.1920928955078125e-07) : S(2.220446049250313e-16);  // finfo eps
  S* out = static_cast<S*>(g.grad) + n * p;
  if (!a.active[n]) return;  // its outputs as the caller fills them: 0, and finite actions
  V* saved = static_cast<V*>(a.saved) + n * layout.blocks * layout.width;
  const int64_t* length = a.length + n * E;
  // Lane masks of the valid steps, the blocks in use, and the per-agent sums of reinforce_terms.
  int64_t used = 0, episodes = 0, steps = 0;
  for (int64_t e = 0; e < E; e++) {
    if (length[e] > 0) used = (e * T + length[e] + L - 1) / L;
    episodes += length[e] > 0;
    steps += length[e];
  }
  if (episodes == 0) return;
  auto valid = [&](int64_t b) {
    V mask{};
    for (int l = 0; l < L; l++) {
      const int64_t r = b * L + l, e = r / T;
      set_lane(mask, l, e < E && r % T < length[e] ? S(1) : S(0));
    }
    return mask;
  };
  // Steps past a row's end were never written: zero them so they add nothing (0 * garbage may be NaN).
  for (int64_t b = 0; b < used; b++) {
    const V mask = valid(b);
    for (int k = 0; k < layout.width; k++)
      saved[b * layout.width + k] = select(mask != S(0), saved[b * layout.width + k], V{});
  }
  S mean = 0, std = 0;
  if (o.baseline_mean || o.normalize_returns) {
    S total = 0;
    for (int64_t b = 0; b < used; b++)
      for (int l = 0; l < L; l++) total += lane(saved[b * layout.width + layout.ret()], l);
    mean = total / S(steps);
    if (o.normalize_returns) {
      S squares = 0;
      for (int64_t b = 0; b < used; b++) {
        const V mask = valid(b);
        const V centred = (saved[b * layout.width + layout.ret()] - mean) * mask;
        for (int l = 0; l < L; l++) squares += lane(centred, l) * lane(centred, l);
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
      for (int l = 0; l < L; l++) set_lane(w, l, lane(w, l) * std::pow(gamma, S((b * L + l) % T)));
    }
    const V coef = -w * per_episode * mask;  // d loss / d log pi at each step
    V* d_loc = &heads[b * 2 * kActionDim];
    V* d_pre = d_loc + kActionDim;
    V scale[kActionDim];
    const V log_prob = log_prob_backward(env, blk + layout.loc(), blk + layout.pre(), blk + layout.action(),
                                         coef * reduce, d_loc, d_pre, scale);
    for (int m = 0; m < kActionDim; m++)
      for (int l = 0; l < L; l++) {
        if (lane(mask, l) == 0) continue;
        std_sum += lane(scale[m], l);
        finite = finite && std::isfinite(lane(blk[layout.action() + m], l));
      }
    for (int l = 0; l < L; l++) loss += lane(mask, l) != 0 ? lane(coef, l) * reduce * lane(log_prob, l) : S(0);
    backward_deltas(net, static_cast<const S*>(a.params) + n * p, blk + layout.acts(), d_loc, d_pre,
                    deltas + b * act_w);
  }
  // The weights' gradients, layer by layer, as sums over the blocks (weight_grad), then the lanes.
  for (int k = 0; k < p; k++) grad[k] = V{};
  for (int l = 0; l < net.n_hidden + 2; l++) {
    const int n_out = net.out(l), n_in = net.width[l];
    const int prev = l < net.n_hidden ? l - 1 : net.n_hidden - 1;
    const V* input = prev < 0 ? saved : saved + layout.acts() + net.act_offset[prev];
    const V* d = l < net.n_hidden ? deltas + net.act_offset[l] : heads + (l - net.n_hidden) * kActionDim;
    const int d_stride = l < net.n_hidden ? act_w : 2 * kActionDim;
    V* gw = grad + net.offset[l];
    weight_grad(d, d_stride, input, layout.width, n_out, n_in, used, gw, gw + n_out * n_in);
  }
  for (int k = 0; k < p; k++) {
    S sum = 0;
    for (int l = 0; l < L; l++) sum += lane(grad[k], l);
    out[k] = sum;
  }
  g.loss[n] = loss;
  g.std_mean[n] = std_sum / S(steps * kActionDim);
  g.actions_finite[n] = finite;
}

// The network as the entry points take it (ops._net packs it): hidden widths after the first n_hidden unread.
struct NetSpec {
  int64_t in_dim, n_hidden, activation;
  double min_std, dist_eps;
  int64_t hidden[kMaxLayers];
};

DK_HD Net make_net(const NetSpec& spec) {
  Net net{};
  net.in_dim = static_cast<int>(spec.in_dim), net.n_hidden = static_cast<int>(spec.n_hidden);
  net.activation = static_cast<int>(spec.activation), net.min_std = spec.min_std, net.dist_eps = spec.dist_eps;
  int off = 0, in = net.in_dim;
  for (int l = 0; l < net.n_hidden + 2; l++) {
    const int n = l < net.n_hidden ? static_cast<int>(spec.hidden[l]) : kActionDim;
    if (l < net.n_hidden) net.act_offset[l] = net.activations, net.activations += n;
    net.offset[l] = off;
    net.width[l] = in;
    off += n * in + n;
    if (l < net.n_hidden) in = n;
  }
  net.params = off;
  return net;
}

// max(net.activations, 1): the scratch vectors of a network's hidden outputs.
DK_HD inline int activation_width(const Net& net) { return net.activations > 0 ? net.activations : 1; }

// ------------------------------------------------------------------------------------------------
// The engines. Each runs fly_block over the rows (fly) and reinforce_agent over the agents (grad)
// of a call. Every entry point reads one array of 8-byte words, a Call field by field (ops._launch
// packs it): the Launch, what either target needs (the CPU's thread count, the GPU's stream and
// scratch memory: dk_cuda_scratch_size scalars the caller allocates, so PyTorch's caching allocator
// owns all device memory; the other target ignores them), the network and the op's arguments.
struct Launch {
  int64_t threads;
  void* stream;
  void* scratch;
};

template <class Args>
struct Call {
  Launch on;
  NetSpec spec;
  Args a;
};

// What the size queries read: the network, then the rows flown, the agents updated, and their
// episodes and steps.
struct Sizes {
  NetSpec spec;
  int64_t rows, agents, episodes, steps;
};

template <class T>
T unpack(const void* words) {
  T t;
  std::memcpy(&t, words, sizeof t);
  return t;
}

#if DK_CPU
// The CPU engine: threads over blocks of lanes() drones. The scalar engine (-DDK_SCALAR_ENGINE)
// is the same with one drone per block: the code each CUDA thread runs.
#ifdef DK_SCALAR_ENGINE
using Lanes = Real;
#else
using Lanes = std::conditional_t<DK_DOUBLE != 0, D, F>;
#endif

template <class Work>
__attribute__((flatten)) void run_range(const Work& work, int64_t scratch, int64_t first, int64_t last) {
  std::vector<Lanes> memory(scratch);
  for (int64_t i = first; i < last; i++) work(i, memory.data());
}

// work(i, scratch) for i < count, the items split over the threads, each with `scratch` vectors.
template <class Work>
int64_t run(int64_t count, int64_t scratch, const Launch& on, Work work) {
  const int64_t workers = count < on.threads ? count : on.threads;
  if (workers <= 1) {  // one worker: this thread (a thread's start and join would cost each call)
    run_range(work, scratch, 0, count);
    return 0;
  }
  std::vector<std::thread> pool;
  for (int64_t k = 0; k < workers; k++)
    pool.emplace_back([&, k] { run_range(work, scratch, count * k / workers, count * (k + 1) / workers); });
  for (auto& th : pool) th.join();
  return 0;
}

#elif defined(__CUDACC__)
// The CUDA engine: one thread per item (a row, or an agent), each running the single-source loops
// with V = Real on its slice of the caller's scratch. Launches go on the caller's stream; nothing
// synchronises. Returns the CUDA error code of the launch.
using Lanes = Real;
constexpr int kThreadsPerBlock = 128;

template <class Work>
__global__ void run_kernel(int64_t count, int64_t scratch, Real* memory, Work work) {
  const int64_t i = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x;
  if (i < count) work(i, memory + i * scratch);
}

template <class Work>
int64_t run(int64_t count, int64_t scratch, const Launch& on, Work work) {
  const auto grid = static_cast<unsigned>((count + kThreadsPerBlock - 1) / kThreadsPerBlock);
  if (count > 0)
    run_kernel<<<grid, kThreadsPerBlock, 0, static_cast<cudaStream_t>(on.stream)>>>(
        count, scratch, static_cast<Real*>(on.scratch), work);
  return static_cast<int64_t>(cudaGetLastError());
}
#endif

#if DK_CPU || defined(__CUDACC__)
constexpr int64_t lanes() { return lanes_of<Lanes>(); }
constexpr int64_t blocks_of(int64_t rows) { return (rows + lanes() - 1) / lanes(); }

// The scratch vectors of a block of rows flown (the lanes' weights, with lanes; the hidden outputs;
// the inputs) and of an agent's gradient (deltas and heads of every saved block; the gradient).
int64_t fly(const Net& net, const RolloutArgs& a, const Launch& on) {
  const int64_t w = lanes() > 1 ? net.params : 0, acts = activation_width(net);
  return run(blocks_of(a.rows), w + acts + net.in_dim, on,
             [=] DK_HD(int64_t b, Lanes* s) { fly_block(net, a, b, s, s + w, s + w + acts); });
}

int64_t grad(const Net& net, const GradArgs& g, const Launch& on) {
  const Saved layout = Saved::of(net, g.roll.episodes, g.roll.steps, lanes());
  const int64_t deltas = layout.blocks * activation_width(net), heads = layout.blocks * 2 * kActionDim;
  return run(g.agents, deltas + heads + net.params, on,
             [=] DK_HD(int64_t n, Lanes* s) { reinforce_agent(net, g, n, s, s + deltas, s + deltas + heads); });
}
}  // namespace

extern "C" {

// The names of the constants the kernels read, in order, each followed by a comma; the observation's
// width; the precision of this build's tensors, in bytes: 4 (float32) or 8 (float64).
const char* dk_env_constants() { return DK_ENV_CONSTANTS(DK_NAME); }
const char* dk_disturbance_constants() { return DK_DISTURBANCE_CONSTANTS(DK_NAME); }
int64_t dk_observation_dim(int64_t observed) { return observation_dim(static_cast<int>(observed)); }
int64_t dk_real_bytes() { return sizeof(Real); }
// The entry points' argument lists, numbered: a library built from another version of this file
// (DRONE_TORCHRL_CUDA_LIBRARY names any file) is refused at load instead of called with wrong arguments.
int64_t dk_abi_version() { return 4; }

// Whole episodes, or segments (RolloutArgs; entries after an episode's end are left as they were:
// zeros). Returns 0 (on a GPU: the CUDA error code of the launch).
int64_t dk_rollout(const void* call) {
  const auto c = unpack<Call<RolloutArgs>>(call);
  return fly(make_net(c.spec), c.a, c.on);
}

// One REINFORCE update's episodes and gradient for every active agent: the rollout of dk_rollout
// (start states, noise and disturbance keys drawn from rng), then reinforce_agent.
int64_t dk_reinforce(const void* call) {
  const auto c = unpack<Call<GradArgs>>(call);
  const Net net = make_net(c.spec);
  const int64_t code = fly(net, c.a.roll, c.on);
  return code != 0 ? code : grad(net, c.a, c.on);
}

// The size of dk_reinforce's saved buffer, in scalars.
int64_t dk_saved_size(const void* sizes) {
  const auto q = unpack<Sizes>(sizes);
  const Saved layout = Saved::of(make_net(q.spec), q.episodes, q.steps, lanes());
  return q.agents * layout.blocks * layout.width * lanes();
}

#if !DK_CPU
// Scratch scalars of dk_rollout (rows rows) and dk_reinforce (agents agents).
int64_t dk_cuda_scratch_size(const void* sizes) {
  const auto q = unpack<Sizes>(sizes);
  const Net net = make_net(q.spec);
  const Saved layout = Saved::of(net, q.episodes, q.steps, 1);
  const int64_t per_row = activation_width(net) + net.in_dim;
  const int64_t per_agent = layout.blocks * (activation_width(net) + 2 * kActionDim) + net.params;
  const int64_t fly = q.rows * per_row, grad = q.agents * per_agent;
  return fly > grad ? fly : grad;
}

// The message of a CUDA error code.
const char* dk_cuda_error(int64_t code) { return cudaGetErrorString(static_cast<cudaError_t>(code)); }
#endif

}  // extern "C"

#else  // DK_SCALAR_CHECK
// The scalar check (-DDK_SCALAR_CHECK): the engine's single-source loops with V = float and
// V = double, compiled without the vector types, as a CUDA kernel (one thread per drone) calls them.
// Instantiating them instantiates every DK_HD function they call (no list of those to keep).
template <class V>
void scalar_check() {
  (void)&fly_block<V>, (void)&reinforce_agent<V>;
}
template void scalar_check<float>();
template void scalar_check<double>();

}  // namespace

#endif
