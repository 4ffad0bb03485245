// Right-hand side of the hybrid tank dynamics (plant-model.md, "Dynamics").
// Pure functions of (x, u, params, mode) on Eigen; no LCM, no SUNDIALS.
//
// The vector field is piecewise smooth. Its pieces are described by a Mode,
// fixed between events so that the integrator sees a smooth field; the
// integrator locates the events (root functions below) and recomputes the mode.
#pragma once

#include <array>
#include <cstdint>

#include "plant/core/params.h"

namespace ftc {

// Discrete part of the hybrid state, valid between two events.
struct Mode {
  // Tanks whose pump supplies fuel, and how much (m^3/s), by the innermost-first rule.
  Vec6 pump_draw = Vec6::Zero();
  // Tanks whose pump is live (fuel in the tank, or an empty tank filled by the
  // conduit faster than its pump draws). Their draw min(p_i, remaining demand)
  // is re-evaluated at x, since a pinned tank upstream passes on a draw that
  // varies with x; pump_draw above is its value where the mode was computed.
  std::array<bool, kTanks> pumping{};
  // Engine demand no tank on its wing supplies, m^3/s.
  Vec2 deficit = Vec2::Zero();
  // Open tanks in the source group (at the conduit potential).
  std::array<bool, kTanks> source{};
  // Open tanks below the conduit potential (receive inflow).
  std::array<bool, kTanks> sink{};
  // Sinks that were tied with the group (within kTieTolerance) and left it
  // because their own pump outruns it: they rejoin when it no longer does
  // (their root function is that condition, not their level; dynamics.cpp).
  std::array<bool, kTanks> left{};
  // Empty tanks pinned at 0 whose pump passes on their conduit inflow
  // (inflow not larger than what the pump would draw).
  std::array<bool, kTanks> pinned{};
};

// Flows at a state under a mode, all in m^3/s.
struct Flows {
  Vec6 conduit = Vec6::Zero();  // net conduit exchange, + into the tank
  Vec6 supply = Vec6::Zero();   // fuel pumped to the engines from each tank
  Vec2 deficit = Vec2::Zero();  // unmet engine demand
};

// Classifies the state (ties within kTieTolerance, empty tanks, group members
// that leave the group) and returns the mode in force from x onwards.
Mode ComputeMode(const Vec6& x, const Valves& u, const PlantParams& p);

// Flows at x under a fixed mode (smooth in x).
Flows ComputeFlows(const Vec6& x, const Valves& u, const PlantParams& p, const Mode& mode);

// dx/dt = (conduit - supply) / area at x under a fixed mode.
Vec6 Derivative(const Vec6& x, const Valves& u, const PlantParams& p, const Mode& mode);

// Derivative and flows from one evaluation (the integrator's right-hand side).
void EvaluateField(const Vec6& x, const PlantParams& p, const Mode& mode, Vec6* derivative,
                   Flows* flows);

// Number of root functions used by the integrator.
constexpr int kNumRoots = 2 * kTanks;

// Root functions g(x) whose sign change ends the current mode: a pumping tank
// reaching 0 (for a sink still being filled, a level below 0 is an
// integration error and does not count: dynamics.cpp), a sink reaching the
// conduit level, a sink that left a tie no longer outrunning the group, a
// pinned tank's inflow crossing its pump draw, a source-group member leaving.
// Entries that cannot fire under `mode` are held at a constant 1.
std::array<double, kNumRoots> RootFunctions(const Vec6& x, const Valves& u, const PlantParams& p,
                                            const Mode& mode);

// The root functions' slots in force at x (bit m set: slot m is a function of
// x; the others are held at 1) and the functions themselves, with the field,
// from one evaluation: RootFunctions(x) and Derivative(x).
void FieldAndRoots(const Vec6& x, const PlantParams& p, const Mode& mode, Vec6* derivative,
                   std::array<double, kNumRoots>* roots, std::uint32_t* active);

// The root functions at x with the slots `active` in force whatever x (as
// FieldAndRoots found them at another point of the mode): within a mode each
// is affine in x, so differences of these give their gradients at any x.
std::array<double, kNumRoots> RootFunctionsOf(const Vec6& x, const PlantParams& p,
                                              const Mode& mode, std::uint32_t active);

// Open tanks within this distance (m) of the highest open level form the source group.
constexpr double kTieTolerance = 1e-9;

}  // namespace ftc
