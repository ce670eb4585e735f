// Tiny 3-vector helpers for the per-pixel math (HOST_DEVICE, templated on the scalar: float or double).
#pragma once

#include "ctgs/constants.h"

namespace ctgs {

template <typename S>
struct Vec3 {
  S x, y, z;
};

template <typename S>
HOST_DEVICE inline Vec3<S> make_vec3(S x, S y, S z) {
  Vec3<S> r;
  r.x = x;
  r.y = y;
  r.z = z;
  return r;
}
template <typename S>
HOST_DEVICE inline S dot(const Vec3<S>& a, const Vec3<S>& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}
template <typename S>
HOST_DEVICE inline Vec3<S> operator+(const Vec3<S>& a, const Vec3<S>& b) {
  return make_vec3(a.x + b.x, a.y + b.y, a.z + b.z);
}
template <typename S>
HOST_DEVICE inline Vec3<S> operator-(const Vec3<S>& a, const Vec3<S>& b) {
  return make_vec3(a.x - b.x, a.y - b.y, a.z - b.z);
}
template <typename S>
HOST_DEVICE inline Vec3<S> operator*(S s, const Vec3<S>& a) {
  return make_vec3(s * a.x, s * a.y, s * a.z);
}
template <typename S>
HOST_DEVICE inline Vec3<S>& operator+=(Vec3<S>& a, const Vec3<S>& b) {
  a.x += b.x;
  a.y += b.y;
  a.z += b.z;
  return a;
}

}  // namespace ctgs
