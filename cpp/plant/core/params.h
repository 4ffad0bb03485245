// Plant parameters and fixed sizes of the fuel-transfer system
// (see ../shared/design/plant-model.md, "Nominal parameters").
#pragma once

#include <Eigen/Core>

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

// Moment arms of the tanks about the fuselage axis (tank spacing units).
inline Vec6 MomentArms() {
  Vec6 m;
  m << -3, -2, -1, 1, 2, 3;
  return m;
}

// Pump order per engine, innermost first: E1 from tanks 3,2,1; E2 from 4,5,6 (0-based).
constexpr int kPumpOrder[kEngines][3] = {{2, 1, 0}, {3, 4, 5}};

}  // namespace ftc
