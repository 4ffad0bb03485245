// Plant parameters and fixed sizes of the fuel-transfer system
// (see ../shared/design/plant-model.md, "Nominal parameters").
#pragma once

#include <Eigen/Core>

#include <algorithm>

namespace ftc {

constexpr int kTanks = 6;
constexpr int kEngines = 2;

using Vec6 = Eigen::Matrix<double, kTanks, 1>;
using Vec2 = Eigen::Matrix<double, kEngines, 1>;
using Valves = Eigen::Matrix<int, kTanks, 1>;  // 0 closed, 1 open

// Physical parameters in force at one moment (nominal, or degraded at an age).
struct PlantParams {
  double g = 10.0;           // gravitational acceleration, m/s^2
  Vec6 height = Vec6::Ones();              // tank capacity level h_i, m
  Vec6 area = Vec6::Ones();                // tank cross-section c_i, m^2
  Vec6 resistance = Vec6::Constant(100.0); // valve resistance R_i, (m^2/s^2) / (m^3/s)
  Vec6 pump = Vec6::Constant(0.1);         // pump capacity p_i, m^3/s
  Vec2 demand = Vec2::Constant(0.05);      // engine demand d_j, m^3/s
};

// Whether two parameter sets are the same, field by field.
inline bool SameParams(const PlantParams& a, const PlantParams& b) {
  return a.g == b.g && a.height == b.height && a.area == b.area &&
         a.resistance == b.resistance && a.pump == b.pump && a.demand == b.demand;
}

// Levels below this (m) are empty: set to exactly 0 at segment boundaries;
// each snap moves at most 1e-12 m^3 of fuel, well inside the conservation
// tests' 1e-10.
constexpr double kEmptySnap = 1e-12;

// Clamps six levels x[0..5] to [0, height] and snaps those below kEmptySnap to
// 0 (rounding leaves such residues where a tank empties exactly at the end of
// a step). Returns whether any level changed.
inline bool ClampLevels(double* x, const Vec6& height) {
  bool changed = false;
  for (int i = 0; i < kTanks; ++i) {
    double v = std::clamp(x[i], 0.0, height[i]);
    if (v < kEmptySnap) v = 0.0;
    changed = changed || v != x[i];
    x[i] = v;
  }
  return changed;
}

// Moment arms of the tanks about the fuselage axis (tank spacing units).
inline Vec6 MomentArms() {
  Vec6 m;
  m << -3, -2, -1, 1, 2, 3;
  return m;
}

// Pump order per engine, innermost first: E1 from tanks 3,2,1; E2 from 4,5,6 (0-based).
constexpr int kPumpOrder[kEngines][3] = {{2, 1, 0}, {3, 4, 5}};

}  // namespace ftc
