// The pipeline's per-run numerical step compiled: fixed-lag smoother, regressor, base rows and
// predicted torque for the samples of one processing run, in one call (see compiled.py).
//
// Same definitions as the Python path it stands in for (tests hold the two equal):
// - smoother: signals.FixedLagSmoother (local polynomial least squares over 2L+1 samples in
//   centred, scaled time u = (t - t_c) / h, h = half the window's span; value, first and
//   second derivative at the centre; no window across a stamp gap larger than max_gap),
// - regressor: robot.RobotModel.regressor, i.e. pinocchio's computeJointTorqueRegressor
//   (standard parameters [m, mx, my, mz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz] of each body about its
//   joint frame origin, in that frame) by the Newton-Euler recursion of regressor_batch.py, in
//   joint frames; then the per-joint extra columns fv, fc, fo, Ia,
// - rows [Yb | tau] (base columns, then the torque) and the prediction Yb theta.
// Units SI; joints and parameters in the robot's order (robot.param_names).
//
// push_cdr also takes the run's input as it comes from the middleware: sensor_msgs/JointState
// CDR messages, decoded (bagio.JointStateDecoder's layout), columns in the robot's order by a
// layout the pipeline registered, stamps in seconds since its epoch; when every message is
// clean (decodable, known layout, lengths right, values finite, stamps increasing after the
// last one) it pushes them, else it changes nothing and the pipeline's Python validation
// (which counts the rejections) takes the run. decode_joint_states decodes runs of such
// messages that share a layout into arrays at once. And the output side: fill_joint_states
// serializes JointState messages as bagio.encode_joint_states does (its compiled path).
// And factor_information, the recursive estimator's Cholesky update with its solution.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <map>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace py = pybind11;
using Array = py::array_t<double, py::array::c_style | py::array::forcecast>;
using Index = py::array_t<long long, py::array::c_style | py::array::forcecast>;

namespace {

using V3 = std::array<double, 3>;
using M3 = std::array<double, 9>;   // row major

V3 add(const V3 &a, const V3 &b) { return {a[0] + b[0], a[1] + b[1], a[2] + b[2]}; }
V3 scale(const V3 &a, double s) { return {a[0] * s, a[1] * s, a[2] * s}; }
double dot(const V3 &a, const V3 &b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
V3 cross(const V3 &a, const V3 &b) {
  return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
V3 mul(const M3 &R, const V3 &v) {
  return {R[0] * v[0] + R[1] * v[1] + R[2] * v[2], R[3] * v[0] + R[4] * v[1] + R[5] * v[2],
          R[6] * v[0] + R[7] * v[1] + R[8] * v[2]};
}
V3 mul_t(const M3 &R, const V3 &v) {   // R^T v
  return {R[0] * v[0] + R[3] * v[1] + R[6] * v[2], R[1] * v[0] + R[4] * v[1] + R[7] * v[2],
          R[2] * v[0] + R[5] * v[1] + R[8] * v[2]};
}
M3 mul(const M3 &A, const M3 &B) {
  M3 C{};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      C[3 * r + c] = A[3 * r] * B[c] + A[3 * r + 1] * B[3 + c] + A[3 * r + 2] * B[6 + c];
  return C;
}
// Rotation by angle q about the unit axis s (Rodrigues).
M3 rotation(const V3 &s, double q) {
  const double c = std::cos(q), sn = std::sin(q), v = 1.0 - c;
  return {c + s[0] * s[0] * v,        s[0] * s[1] * v - s[2] * sn, s[0] * s[2] * v + s[1] * sn,
          s[1] * s[0] * v + s[2] * sn, c + s[1] * s[1] * v,        s[1] * s[2] * v - s[0] * sn,
          s[2] * s[0] * v - s[1] * sn, s[2] * s[1] * v + s[0] * sn, c + s[2] * s[2] * v};
}

enum Extra { kViscous = 0, kCoulomb = 1, kOffset = 2, kRotor = 3 };

struct Joint {
  int parent;      // index of the parent joint, -1 for the universe
  int robot;       // the joint's index in the robot's order (row of Y, block of parameters)
  bool revolute;   // else prismatic
  M3 R0;           // placement in the parent joint frame at q = 0
  V3 p0, s;        // its translation; unit axis in the joint frame
  std::vector<int> chain;   // ancestors-or-self, root first
};

// A sensor_msgs/JointState CDR message's header stamp (ns), name sequence and arrays.
struct Message {
  const char *data = nullptr;
  std::int64_t stamp = 0;
  std::string_view names;   // the name sequence's CDR bytes
  size_t name_count = 0;
  std::array<size_t, 3> offsets{}, counts{};
};

std::uint32_t u32(const char *p) {
  std::uint32_t v;
  std::memcpy(&v, p, 4);
  return v;
}

// parse reads values in the host's byte order: the decoders decline on big-endian hosts.
bool little_endian_host() {
  const std::uint16_t one = 1;
  return *reinterpret_cast<const unsigned char *>(&one) == 1;
}

// Little-endian JointState CDR (bagio.JointStateDecoder._fast's offsets: alignment relative
// to the body at offset 4; a float64 sequence is 8-aligned only when not empty).
bool parse(const char *d, size_t n, Message *msg) {
  if (n < 16 || d[0] != 0 || d[1] != 1) return false;
  std::int32_t sec;
  std::memcpy(&sec, d + 4, 4);
  msg->stamp = static_cast<std::int64_t>(sec) * 1000000000LL + u32(d + 8);
  const size_t flen = u32(d + 12);
  size_t p = 16 + flen;
  if (flen == 0 || p > n || d[p - 1]) return false;
  p = (p + 3) & ~size_t{3};
  const size_t start = p;
  if (p + 4 > n) return false;
  const size_t names = u32(d + p);
  p += 4;
  if (5 * names > n - p) return false;
  for (size_t k = 0; k < names; ++k) {
    p = (p + 3) & ~size_t{3};
    if (p + 4 > n) return false;
    const size_t length = u32(d + p);
    const size_t end = p + 4 + length;
    if (length == 0 || end > n || d[end - 1]) return false;
    p = end;
  }
  msg->names = std::string_view(d + start, p - start);
  msg->name_count = names;
  for (int f = 0; f < 3; ++f) {
    p = (p + 3) & ~size_t{3};
    if (p + 4 > n) return false;
    const size_t c = u32(d + p);
    p += 4;
    if (c) {
      p = ((p + 3) & ~size_t{7}) + 4;
      if (p > n || c > (n - p) / 8) return false;
    }
    msg->offsets[f] = p;
    msg->counts[f] = c;
    p += 8 * c;
  }
  msg->data = d;
  return true;
}

class Step {
 public:
  // The robot's kinematic tree, joints parents first: parent index (-1: universe), robot
  // index, placement (4, 4) in the parent joint frame, kind (0 revolute or continuous,
  // 1 prismatic) and unit axis in the joint frame; gravity (3,) m/s^2 in the universe frame.
  // extras: codes of the per-joint extra columns; base_columns (b,): the base parameters'
  // columns of Y; the smoother's half window, polynomial order and max_gap (s).
  Step(Index parents, Index robot_index, Array placements, Index kinds, Array axes,
       Array gravity, Index extras, double coulomb_velocity, Index base_columns,
       int half_window, int order, double max_gap)
      : coulomb_velocity_(coulomb_velocity), half_window_(half_window), order_(order),
        max_gap_(max_gap) {
    auto P = parents.unchecked<1>();
    auto I = robot_index.unchecked<1>();
    auto M = placements.unchecked<3>();
    auto K = kinds.unchecked<1>();
    auto A = axes.unchecked<2>();
    n_ = static_cast<int>(P.shape(0));
    if (I.shape(0) != n_ || M.shape(0) != n_ || K.shape(0) != n_ || A.shape(0) != n_ ||
        M.shape(1) != 4 || M.shape(2) != 4 || A.shape(1) != 3)
      throw std::invalid_argument("joint tree arrays disagree in shape");
    if (half_window < 1 || order < 2 || order > 4 || order > 2 * half_window || !(max_gap > 0))
      throw std::invalid_argument("bad smoother settings");
    std::vector<bool> seen(n_, false);
    for (int j = 0; j < n_; ++j) {
      Joint joint;
      joint.parent = static_cast<int>(P(j));
      joint.robot = static_cast<int>(I(j));
      if (joint.parent < -1 || joint.parent >= j || joint.robot < 0 || joint.robot >= n_ ||
          seen[joint.robot])
        throw std::invalid_argument("parents must come first and robot indices be a permutation");
      seen[joint.robot] = true;
      joint.revolute = K(j) == 0;
      for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) joint.R0[3 * r + c] = M(j, r, c);
        joint.p0[r] = M(j, r, 3);
        joint.s[r] = A(j, r);
      }
      if (joint.parent >= 0) joint.chain = joints_[joint.parent].chain;
      joint.chain.push_back(j);
      joints_.push_back(joint);
    }
    auto g = gravity.unchecked<1>();
    gravity_ = {g(0), g(1), g(2)};
    auto E = extras.unchecked<1>();
    for (py::ssize_t k = 0; k < E.shape(0); ++k) extras_.push_back(static_cast<int>(E(k)));
    num_params_ = n_ * (10 + static_cast<int>(extras_.size()));
    auto B = base_columns.unchecked<1>();
    for (py::ssize_t k = 0; k < B.shape(0); ++k) {
      base_.push_back(static_cast<int>(B(k)));
      if (base_.back() < 0 || base_.back() >= num_params_)
        throw std::invalid_argument("base column out of range");
    }
    motion_.resize(n_);
    w_.resize(n_);
    wd_.resize(n_);
    a_.resize(n_);
  }

  int buffered() const { return static_cast<int>(t_.size()); }

  void reset() {
    t_.clear();
    x_.clear();
  }

  // Push samples t (N,) s, x (N, c) (strictly increasing stamps after the buffered ones,
  // finite values: the pipeline checked them); c = 2n as [q | tau], or 3n as [q | qd | tau]
  // when ``measured_velocity``. Returns (t_c (M,), q, qd, qdd, tau (M, n), rows (M, n, b + 1),
  // predicted (M, n) = Yb theta) for every window completed.
  py::tuple push(Array t_new, Array x_new, Array theta, bool measured_velocity) {
    auto tn = t_new.unchecked<1>();
    auto xn = x_new.unchecked<2>();
    const int c = static_cast<int>(xn.shape(1));
    if (xn.shape(0) != tn.shape(0) || c != (measured_velocity ? 3 : 2) * n_)
      throw std::invalid_argument("push: shapes of t or x do not fit the model");
    check(theta, c);
    for (py::ssize_t k = 0; k < tn.shape(0); ++k) {
      t_.push_back(tn(k));
      for (int j = 0; j < c; ++j) x_.push_back(xn(k, j));
    }
    return windows(theta, measured_velocity);
  }

  // The column of each robot joint in messages whose names are ``names`` (message order).
  void set_layout(const std::vector<std::string> &names, Index columns) {
    auto C = columns.unchecked<1>();
    if (C.shape(0) != n_) throw std::invalid_argument("set_layout: one column per joint");
    std::string blob(4, '\0');
    const std::uint32_t count = static_cast<std::uint32_t>(names.size());
    std::memcpy(&blob[0], &count, 4);
    for (const std::string &name : names) {
      blob.resize((blob.size() + 3) & ~size_t{3}, '\0');
      const std::uint32_t length = static_cast<std::uint32_t>(name.size() + 1);
      blob.append(reinterpret_cast<const char *>(&length), 4);
      blob.append(name);
      blob.push_back('\0');
    }
    std::vector<int> &index = layouts_[blob];
    index.assign(n_, 0);
    for (int i = 0; i < n_; ++i) {
      if (C(i) < 0 || C(i) >= static_cast<long long>(names.size()))
        throw std::invalid_argument("set_layout: column out of range");
      index[i] = static_cast<int>(C(i));
    }
    if (layouts_.size() > 64) layouts_ = {{blob, index}};
  }

  // The samples of JointState CDR messages, pushed as ``push`` does (x = [q | tau] or
  // [q | qd | tau], torque = effort), when all are clean (see the top); stamps in seconds
  // since epoch_ns. Returns push's tuple and the newest stamp, or None with nothing changed.
  py::object push_cdr(const py::list &messages, long long epoch_ns, double last_stamp,
                      Array theta, bool measured_velocity) {
    const int c = (measured_velocity ? 3 : 2) * n_;
    check(theta, c);
    if (!little_endian_host()) return py::none();
    const size_t count = messages.size(), old_t = t_.size(), old_x = x_.size();
    auto undo = [&]() {
      t_.resize(old_t);
      x_.resize(old_x);
      return py::none();
    };
    double last = last_stamp;
    for (size_t k = 0; k < count; ++k) {
      PyObject *item = messages[k].ptr();
      if (!PyBytes_Check(item)) return undo();
      Message msg;
      if (!parse(PyBytes_AS_STRING(item), static_cast<size_t>(PyBytes_GET_SIZE(item)), &msg))
        return undo();
      auto layout = layouts_.find(msg.names);
      if (layout == layouts_.end()) return undo();
      const size_t width = msg.name_count;
      if (msg.counts[0] != width || msg.counts[2] != width ||
          (msg.counts[1] != 0 && msg.counts[1] != width) ||
          (measured_velocity && msg.counts[1] != width))
        return undo();
      const double t = static_cast<double>(msg.stamp - epoch_ns) * 1e-9;
      if (!(t > last)) return undo();
      last = t;
      t_.push_back(t);
      const std::vector<int> &index = layout->second;
      for (int f = 0; f < 3; ++f) {
        if (f == 1 && !measured_velocity) continue;
        const char *values = msg.data + msg.offsets[f];
        for (int i = 0; i < n_; ++i) {
          double v;
          std::memcpy(&v, values + 8 * index[i], 8);
          if (!std::isfinite(v)) return undo();
          x_.push_back(v);
        }
      }
    }
    py::tuple out = windows(theta, measured_velocity);
    return py::make_tuple(out[0], out[1], out[2], out[3], out[4], out[5], out[6], last);
  }

 private:
  void check(const Array &theta, int c) {
    if (theta.ndim() != 1 || theta.shape(0) != static_cast<py::ssize_t>(base_.size()))
      throw std::invalid_argument("push: theta must have one value per base parameter");
    if (!t_.empty() && c != channels_)
      throw std::invalid_argument("push: channel count changed without reset()");
    if (t_.empty()) channels_ = c;
  }

  // Smooth and regress every window the buffer completes (push's outputs).
  py::tuple windows(const Array &theta, bool measured_velocity) {
    auto th = theta.unchecked<1>();
    const int c = channels_;
    const int b = static_cast<int>(base_.size());
    const int N = static_cast<int>(t_.size()), L = half_window_, K = 2 * L + 1;
    // Windows [s, s + K) within one segment (no gap > max_gap); the buffer keeps the last
    // segment's newest 2L samples.
    std::vector<int> segment(N, 0), starts;
    for (int k = 1; k < N; ++k) segment[k] = segment[k - 1] + (t_[k] - t_[k - 1] > max_gap_);
    for (int s = 0; s + K <= N; ++s)
      if (segment[s] == segment[s + K - 1]) starts.push_back(s);
    int last = N - 1;
    while (last > 0 && segment[last - 1] == segment[N - 1]) --last;
    const int M = static_cast<int>(starts.size());
    py::array_t<double> tc(M), q({M, n_}), qd({M, n_}), qdd({M, n_}), tau({M, n_}),
        predicted({M, n_}), rows({M, n_, b + 1});
    {
      auto Tc = tc.mutable_unchecked<1>();
      auto Q = q.mutable_unchecked<2>();
      auto Qd = qd.mutable_unchecked<2>();
      auto Qdd = qdd.mutable_unchecked<2>();
      auto U = tau.mutable_unchecked<2>();
      auto Pr = predicted.mutable_unchecked<2>();
      auto R = rows.mutable_unchecked<3>();
      py::gil_scoped_release unlocked;
      const int p = order_ + 1;
      std::vector<double> powers(static_cast<size_t>(p) * K), coef(static_cast<size_t>(p) * c);
      std::vector<double> y(static_cast<size_t>(n_) * num_params_);
      for (int m = 0; m < M; ++m) {
        const int s = starts[m];
        const double centre = t_[s + L], h = 0.5 * (t_[s + K - 1] - t_[s]);
        for (int k = 0; k < K; ++k) {
          const double u = (t_[s + k] - centre) / h;
          powers[k] = 1.0;
          for (int e = 1; e < p; ++e) powers[e * K + k] = powers[(e - 1) * K + k] * u;
        }
        fit(powers.data(), p, K, &x_[static_cast<size_t>(s) * c], c, coef.data());
        Tc(m) = centre;
        for (int i = 0; i < n_; ++i) {
          Q(m, i) = coef[i];
          if (measured_velocity) {
            Qd(m, i) = coef[n_ + i];
            Qdd(m, i) = coef[c + n_ + i] / h;
          } else {
            Qd(m, i) = coef[c + i] / h;
            Qdd(m, i) = 2.0 * coef[2 * c + i] / (h * h);
          }
          U(m, i) = coef[c - n_ + i];
        }
        regressor(&Q(m, 0), &Qd(m, 0), &Qdd(m, 0), y.data());
        for (int i = 0; i < n_; ++i) {
          const double *yi = y.data() + static_cast<size_t>(i) * num_params_;
          double sum = 0.0;
          for (int j = 0; j < b; ++j) {
            R(m, i, j) = yi[base_[j]];
            sum += yi[base_[j]] * th(j);
          }
          R(m, i, b) = U(m, i);
          Pr(m, i) = sum;
        }
      }
    }
    const int keep = N ? std::max(last, N - 2 * L) : 0;
    if (keep > 0) {
      t_.erase(t_.begin(), t_.begin() + keep);
      x_.erase(x_.begin(), x_.begin() + static_cast<std::ptrdiff_t>(keep) * c);
    }
    return py::make_tuple(tc, q, qd, qdd, tau, rows, predicted);
  }

 public:
  // Y (N, n, p) for samples (N, n) of q, qd, qdd: RobotModel.regressor's definition.
  py::array_t<double> regress(Array q, Array qd, Array qdd) {
    auto Q = q.unchecked<2>();
    auto V = qd.unchecked<2>();
    auto A = qdd.unchecked<2>();
    const py::ssize_t N = Q.shape(0);
    if (Q.shape(1) != n_ || V.shape(0) != N || V.shape(1) != n_ || A.shape(0) != N ||
        A.shape(1) != n_)
      throw std::invalid_argument("regress: q, qd, qdd must be (N, n)");
    py::array_t<double> out({N, static_cast<py::ssize_t>(n_),
                             static_cast<py::ssize_t>(num_params_)});
    auto O = out.mutable_unchecked<3>();
    for (py::ssize_t k = 0; k < N; ++k)
      regressor(Q.data(k, 0), V.data(k, 0), A.data(k, 0), O.mutable_data(k, 0, 0));
    return out;
  }

 private:
  // Least-squares polynomial coefficients coef (p, c) of the K samples x (K, c) (rows c
  // apart) with Vandermonde rows powers (p, K): the normal equations, by Cholesky.
  static void fit(const double *powers, int p, int K, const double *x, int c, double *coef) {
    double G[25], Lc[25];
    for (int a = 0; a < p; ++a)
      for (int e = 0; e <= a; ++e) {
        double sum = 0.0;
        for (int k = 0; k < K; ++k) sum += powers[a * K + k] * powers[e * K + k];
        G[a * p + e] = G[e * p + a] = sum;
      }
    for (int a = 0; a < p; ++a)
      for (int e = 0; e <= a; ++e) {
        double sum = G[a * p + e];
        for (int k = 0; k < e; ++k) sum -= Lc[a * p + k] * Lc[e * p + k];
        Lc[a * p + e] = a == e ? std::sqrt(sum) : sum / Lc[e * p + e];
      }
    std::fill(coef, coef + static_cast<size_t>(p) * c, 0.0);
    for (int k = 0; k < K; ++k)
      for (int a = 0; a < p; ++a) {
        const double w = powers[a * K + k];
        for (int j = 0; j < c; ++j) coef[a * c + j] += w * x[k * c + j];
      }
    for (int j = 0; j < c; ++j) {   // L L' coef = rhs
      for (int a = 0; a < p; ++a) {
        double sum = coef[a * c + j];
        for (int k = 0; k < a; ++k) sum -= Lc[a * p + k] * coef[k * c + j];
        coef[a * c + j] = sum / Lc[a * p + a];
      }
      for (int a = p - 1; a >= 0; --a) {
        double sum = coef[a * c + j];
        for (int k = a + 1; k < p; ++k) sum -= Lc[k * p + a] * coef[k * c + j];
        coef[a * c + j] = sum / Lc[a * p + a];
      }
    }
  }

  // Full regressor rows (n, p) of one sample into y; q, qd, qdd (n,) in the robot's order.
  void regressor(const double *q, const double *qd, const double *qdd, double *y) {
    std::fill(y, y + static_cast<size_t>(n_) * num_params_, 0.0);
    std::vector<V3> &w = w_, &wd = wd_, &a = a_;
    for (int j = 0; j < n_; ++j) {
      const Joint &J = joints_[j];
      const double x = q[J.robot], xd = qd[J.robot], xdd = qdd[J.robot];
      const M3 R = J.revolute ? mul(J.R0, rotation(J.s, x)) : J.R0;
      const V3 pos = J.revolute ? J.p0 : add(J.p0, mul(J.R0, scale(J.s, x)));
      V3 wp{0, 0, 0}, wdp{0, 0, 0}, ap = scale(gravity_, -1.0);
      if (J.parent >= 0) {
        wp = w[J.parent];
        wdp = wd[J.parent];
        ap = a[J.parent];
      }
      // kinematics of the joint frame, in it: w, wd, origin acceleration minus gravity
      w[j] = mul_t(R, wp);
      wd[j] = mul_t(R, wdp);
      a[j] = mul_t(R, add(ap, add(cross(wdp, pos), cross(wp, cross(wp, pos)))));
      const V3 rate = scale(J.s, xd);
      if (J.revolute) {
        wd[j] = add(wd[j], add(scale(J.s, xdd), cross(w[j], rate)));
        w[j] = add(w[j], rate);
      } else {
        a[j] = add(a[j], add(scale(J.s, xdd), scale(cross(w[j], rate), 2.0)));
      }
      // motion subspaces (linear at the origin; angular) of the ancestors-or-self, here
      std::vector<std::array<V3, 2>> &u = motion_[j];
      u.resize(J.chain.size());
      for (size_t k = 0; k + 1 < J.chain.size(); ++k) {
        const std::array<V3, 2> &up = motion_[J.parent][k];
        u[k] = {mul_t(R, add(up[0], cross(up[1], pos))), mul_t(R, up[1])};
      }
      u.back() = J.revolute ? std::array<V3, 2>{V3{0, 0, 0}, J.s}
                            : std::array<V3, 2>{J.s, V3{0, 0, 0}};
      const V3 &W = w[j], &D = wd[j], &Acc = a[j];
      const double ww = dot(W, W);
      for (size_t k = 0; k < J.chain.size(); ++k) {
        const V3 &ul = u[k][0], &ua = u[k][1];
        double *yk = y + static_cast<size_t>(joints_[J.chain[k]].robot) * num_params_ +
                     10 * J.robot;
        yk[0] = dot(ul, Acc);
        const V3 mc = add(add(cross(ul, D), scale(W, dot(ul, W))),
                          add(scale(ul, -ww), cross(Acc, ua)));
        yk[1] = mc[0];
        yk[2] = mc[1];
        yk[3] = mc[2];
        const V3 cw = cross(ua, W);   // B(ua, wd) + B(ua x w, w), B(x, y) = x' I y
        yk[4] = ua[0] * D[0] + cw[0] * W[0];
        yk[5] = ua[0] * D[1] + ua[1] * D[0] + cw[0] * W[1] + cw[1] * W[0];
        yk[6] = ua[0] * D[2] + ua[2] * D[0] + cw[0] * W[2] + cw[2] * W[0];
        yk[7] = ua[1] * D[1] + cw[1] * W[1];
        yk[8] = ua[1] * D[2] + ua[2] * D[1] + cw[1] * W[2] + cw[2] * W[1];
        yk[9] = ua[2] * D[2] + cw[2] * W[2];
      }
    }
    const int ne = static_cast<int>(extras_.size());
    for (int i = 0; i < n_; ++i) {
      double *yi = y + static_cast<size_t>(i) * num_params_ + 10 * n_ + i * ne;
      for (int e = 0; e < ne; ++e) {
        switch (extras_[e]) {
          case kViscous: yi[e] = qd[i]; break;
          case kCoulomb:
            yi[e] = coulomb_velocity_ > 0 ? std::tanh(qd[i] / coulomb_velocity_)
                                          : static_cast<double>((qd[i] > 0) - (qd[i] < 0));
            break;
          case kRotor: yi[e] = qdd[i]; break;
          default: yi[e] = 1.0; break;
        }
      }
    }
  }

  std::vector<Joint> joints_;
  // per-sample work: per joint its motion subspaces (per chain entry), w, wd, a
  std::vector<std::vector<std::array<V3, 2>>> motion_;
  std::vector<V3> w_, wd_, a_;
  V3 gravity_{};
  int n_ = 0, num_params_ = 0, channels_ = 0;
  std::vector<int> extras_, base_;
  double coulomb_velocity_;
  int half_window_, order_;
  double max_gap_;
  std::vector<double> t_, x_;
  // names CDR bytes -> columns (std::less<>: looked up by string_view, no copy)
  std::map<std::string, std::vector<int>, std::less<>> layouts_;
};

// JointState CDR messages sharing one name sequence and array lengths, decoded at once:
// (stamps (M,) int64 ns, the name sequence's CDR bytes, position, velocity, effort (M, k)),
// or None when there are none, or one is not bytes, not little-endian CDR (parse) or differs
// from the first in names or lengths (the caller decodes such runs message by message).
py::object decode_joint_states(const py::list &messages) {
  const size_t M = messages.size();
  if (!little_endian_host() || M == 0) return py::none();
  std::vector<Message> parsed(M);
  for (size_t k = 0; k < M; ++k) {
    PyObject *item = PyList_GET_ITEM(messages.ptr(), k);
    if (!PyBytes_Check(item) ||
        !parse(PyBytes_AS_STRING(item), static_cast<size_t>(PyBytes_GET_SIZE(item)),
               &parsed[k]) ||
        parsed[k].names != parsed[0].names || parsed[k].counts != parsed[0].counts)
      return py::none();
  }
  const auto rows = static_cast<py::ssize_t>(M);
  py::array_t<long long> stamps(rows);
  long long *S = stamps.mutable_data();
  for (size_t k = 0; k < M; ++k) S[k] = parsed[k].stamp;
  std::array<py::array_t<double>, 3> fields;
  for (int f = 0; f < 3; ++f) {
    const size_t c = parsed[0].counts[f];
    fields[f] = py::array_t<double>({rows, static_cast<py::ssize_t>(c)});
    double *out = fields[f].mutable_data();
    for (size_t k = 0; k < M; ++k)
      std::memcpy(out + k * c, parsed[k].data + parsed[k].offsets[f], 8 * c);
  }
  const std::string_view names = parsed[0].names;
  return py::make_tuple(stamps, py::bytes(names.data(), names.size()), fields[0], fields[1],
                        fields[2]);
}

// JointState CDR messages filled in from a template (bagio.encode_joint_states' layout: the
// CDR of a message with the same names and array lengths, zero stamp and values): one message
// per stamp (N,) int64 ns, with the rows of position, velocity, effort (N, k) or None at the
// byte offsets (3,) of the template's arrays.
py::list fill_joint_states(py::array_t<std::uint8_t, py::array::c_style> templ, Index offsets,
                           Index stamps, py::object position, py::object velocity,
                           py::object effort) {
  auto S = stamps.unchecked<1>();
  auto O = offsets.unchecked<1>();
  const py::ssize_t N = S.shape(0), size = templ.size();
  if (O.shape(0) != 3) throw std::invalid_argument("fill_joint_states: three offsets");
  std::array<Array, 3> arrays;
  std::array<py::ssize_t, 3> widths{0, 0, 0};
  const py::object fields[3] = {position, velocity, effort};
  for (int f = 0; f < 3; ++f) {
    if (fields[f].is_none()) continue;
    arrays[f] = Array::ensure(fields[f]);
    if (!arrays[f] || arrays[f].ndim() != 2 || arrays[f].shape(0) != N)
      throw std::invalid_argument("fill_joint_states: arrays must be (N, k)");
    widths[f] = arrays[f].shape(1);
    if (O(f) < 0 || O(f) + 8 * widths[f] > size)
      throw std::invalid_argument("fill_joint_states: an array does not fit the template");
  }
  if (size < 12) throw std::invalid_argument("fill_joint_states: template too short");
  py::list out(N);
  for (py::ssize_t m = 0; m < N; ++m) {
    PyObject *bytes = PyBytes_FromStringAndSize(nullptr, size);
    if (bytes == nullptr) throw py::error_already_set();
    char *d = PyBytes_AS_STRING(bytes);
    std::memcpy(d, templ.data(), size);
    long long sec = S(m) / 1000000000LL, nsec = S(m) % 1000000000LL;
    if (nsec < 0) {   // floor division, as np.divmod
      sec -= 1;
      nsec += 1000000000LL;
    }
    const std::int32_t sec32 = static_cast<std::int32_t>(static_cast<std::uint32_t>(sec));
    const std::uint32_t nsec32 = static_cast<std::uint32_t>(nsec);
    std::memcpy(d + 4, &sec32, 4);
    std::memcpy(d + 8, &nsec32, 4);
    for (int f = 0; f < 3; ++f)
      if (widths[f])
        std::memcpy(d + O(f), arrays[f].data(m, 0), 8 * widths[f]);
    out[m] = py::reinterpret_steal<py::object>(bytes);
  }
  return out;
}

// The RLS update's factorisation (estimators.RecursiveLeastSquares, information form) in one
// call: for the augmented information M = old'old + sum_j information_j = [[A, m], [m', s]]
// (k, k) of a factor old (r, k) and per-joint information (n, k, k), the upper-triangular
// F = [[R, z], [0, rho]] with F'F = M (estimators._cholesky_augmented), and what the
// estimator derives from it at full rank (estimators._solve): theta = R^-1 z, R^-1 and the
// column-scaled condition bound ||R / d||_F ||d R^-1||_F. None when M is not finite, A is not
// positive definite, or a result is not finite.
py::object factor_information(Array old_in, Array info_in) {
  if (old_in.ndim() != 2 || info_in.ndim() != 3 || old_in.shape(1) < 2 ||
      info_in.shape(1) != old_in.shape(1) || info_in.shape(2) != old_in.shape(1))
    throw std::invalid_argument("factor_information: old (r, k) and information (n, k, k)");
  const py::ssize_t k = old_in.shape(1), p = k - 1, rows = old_in.shape(0);
  const double *O = old_in.data(), *I = info_in.data();
  for (const Array *a : {&old_in, &info_in})
    if (!std::all_of(a->data(), a->data() + a->size(), [](double v) { return std::isfinite(v); }))
      return py::none();
  // M, lower triangle, row major (row-wise loops below: contiguous inner products)
  std::vector<double> M(k * k, 0.0);
  for (py::ssize_t j = 0; j < info_in.shape(0); ++j, I += k * k)
    for (py::ssize_t r = 0; r < k; ++r)
      for (py::ssize_t c = 0; c <= r; ++c) M[r * k + c] += I[r * k + c];
  for (py::ssize_t i = 0; i < rows; ++i, O += k)
    for (py::ssize_t r = 0; r < k; ++r) {
      if (O[r] == 0.0) continue;   // old is mostly triangular
      for (py::ssize_t c = 0; c <= r; ++c) M[r * k + c] += O[r] * O[c];
    }
  for (double v : M)   // finite inputs can still overflow
    if (!std::isfinite(v)) return py::none();
  // Cholesky A = L L' (R = L'), then L z = m, rho^2 = s - z'z clipped at 0
  std::vector<double> L(p * p, 0.0), z(p), Y(p * p, 0.0);
  for (py::ssize_t i = 0; i < p; ++i) {
    const double *Li = &L[i * p];
    for (py::ssize_t j = 0; j <= i; ++j) {
      const double *Lj = &L[j * p];
      double v = M[i * k + j];
      for (py::ssize_t c = 0; c < j; ++c) v -= Li[c] * Lj[c];
      if (j < i) {
        L[i * p + j] = v / Lj[j];
      } else {
        if (!(v > 0.0)) return py::none();
        L[i * p + i] = std::sqrt(v);
      }
    }
  }
  double zz = 0.0;
  for (py::ssize_t i = 0; i < p; ++i) {
    double v = M[p * k + i];
    for (py::ssize_t c = 0; c < i; ++c) v -= L[i * p + c] * z[c];
    z[i] = v / L[i * p + i];
    zz += z[i] * z[i];
  }
  // Y = L^-1 row by row (R^-1 = Y'), theta = R^-1 z = Y'z
  std::vector<double> theta(p, 0.0);
  for (py::ssize_t i = 0; i < p; ++i) {
    double *Yi = &Y[i * p];
    Yi[i] = 1.0;
    for (py::ssize_t c = 0; c < i; ++c) {
      const double l = L[i * p + c];
      const double *Yc = &Y[c * p];
      for (py::ssize_t j = 0; j <= c; ++j) Yi[j] -= l * Yc[j];
    }
    const double inv = 1.0 / L[i * p + i];
    for (py::ssize_t j = 0; j <= i; ++j) {
      Yi[j] *= inv;
      theta[j] += Yi[j] * z[i];
    }
  }
  // column scale d of R (row norms of L) as estimators._column_scale, then the bound
  std::vector<double> d(p);
  double dmax = 0.0;
  for (py::ssize_t i = 0; i < p; ++i) {
    double v = 0.0;
    for (py::ssize_t c = 0; c <= i; ++c) v += L[i * p + c] * L[i * p + c];
    d[i] = std::sqrt(v);
    dmax = std::max(dmax, d[i]);
  }
  for (py::ssize_t i = 0; i < p; ++i)
    if (!(d[i] > 1e-12 * dmax)) d[i] = std::max(dmax, 1e-300);
  double scaled = 0.0, scaled_inv = 0.0;
  for (py::ssize_t i = 0; i < p; ++i)
    for (py::ssize_t c = 0; c <= i; ++c) {
      const double a = L[i * p + c] / d[i], b = Y[i * p + c] * d[c];
      scaled += a * a;
      scaled_inv += b * b;
    }
  const double bound = std::sqrt(scaled) * std::sqrt(scaled_inv);
  const double rho = std::sqrt(std::max(M[p * k + p] - zz, 0.0));
  bool finite = std::isfinite(bound) && std::isfinite(rho);
  for (py::ssize_t i = 0; i < p && finite; ++i)
    finite = std::isfinite(theta[i]) && std::isfinite(z[i]);
  if (!finite) return py::none();
  Array F_out({k, k}), theta_out(p), inv_out({p, p});
  double *F = F_out.mutable_data(), *X = inv_out.mutable_data();
  std::fill(F, F + k * k, 0.0);
  std::fill(X, X + p * p, 0.0);
  for (py::ssize_t i = 0; i < p; ++i) {
    for (py::ssize_t c = 0; c <= i; ++c) {
      F[c * k + i] = L[i * p + c];
      X[c * p + i] = Y[i * p + c];
    }
    F[i * k + p] = z[i];
  }
  F[p * k + p] = rho;
  std::copy(theta.begin(), theta.end(), theta_out.mutable_data());
  return py::make_tuple(F_out, theta_out, inv_out, bound);
}

}  // namespace

PYBIND11_MODULE(_kernel, m) {
  m.doc() = "The identification pipeline's per-run numerical step, compiled (see compiled.py).";
  py::class_<Step>(m, "Step")
      .def(py::init<Index, Index, Array, Index, Array, Array, Index, double, Index, int, int,
                    double>())
      .def_property_readonly("buffered", &Step::buffered)
      .def("reset", &Step::reset)
      .def("push", &Step::push)
      .def("set_layout", &Step::set_layout)
      .def("push_cdr", &Step::push_cdr)
      .def("regress", &Step::regress);
  m.def("fill_joint_states", &fill_joint_states);
  m.def("decode_joint_states", &decode_joint_states);
  m.def("factor_information", &factor_information);
}
