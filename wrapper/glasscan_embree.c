/*
 * glasscan_embree.c - implementation of glasscan_embree.h over Embree 3 or Embree 4.
 *
 * The API differences handled here: the header directory, and the ray-query signatures
 * (Embree 3 passes an RTCIntersectContext, Embree 4 an optional RTCIntersectArguments).
 */
#include "glasscan_embree.h"

#if defined(GS_EMBREE_MAJOR) && GS_EMBREE_MAJOR >= 4
#include <embree4/rtcore.h>
#else
#include <embree3/rtcore.h>
#endif

#include <math.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#if RTC_VERSION_MAJOR >= 4
#define GS_EMBREE4 1
#else
#define GS_EMBREE4 0
#endif

struct gs_device {
  RTCDevice device;
};

struct gs_scene {
  RTCDevice device;
  RTCScene scene;
  RTCGeometry geom;
  float* vbuf; /* Embree-owned vertex buffer (updated in place) */
  size_t nverts;
  size_t ntris;
};

static _Thread_local char gs_error[512];

static void set_error(const char* what) {
  snprintf(gs_error, sizeof gs_error, "%s", what);
}

static const char* code_name(enum RTCError code) {
  switch (code) {
    case RTC_ERROR_NONE: return "no error";
    case RTC_ERROR_UNKNOWN: return "unknown error";
    case RTC_ERROR_INVALID_ARGUMENT: return "invalid argument";
    case RTC_ERROR_INVALID_OPERATION: return "invalid operation";
    case RTC_ERROR_OUT_OF_MEMORY: return "out of memory";
    case RTC_ERROR_UNSUPPORTED_CPU: return "unsupported CPU";
    case RTC_ERROR_CANCELLED: return "cancelled";
    default: return "unrecognised error";
  }
}

static void error_callback(void* user, enum RTCError code, const char* str) {
  (void)user;
  snprintf(gs_error, sizeof gs_error, "Embree: %s%s%s", code_name(code), str ? ": " : "",
           str ? str : "");
}

/* Returns 0 if the device has no pending error on this thread, else records it and returns -1. */
static int check(RTCDevice device, const char* what) {
  enum RTCError code = rtcGetDeviceError(device);
  if (code == RTC_ERROR_NONE) return 0;
  if (gs_error[0] == '\0') {
    snprintf(gs_error, sizeof gs_error, "Embree: %s during %s", code_name(code), what);
  }
  return -1;
}

const char* gs_embree_version(void) { return RTC_VERSION_STRING; }

const char* gs_last_error(void) { return gs_error; }

gs_device* gs_device_new(const char* config) {
  gs_error[0] = '\0';
  RTCDevice device = rtcNewDevice(config);
  if (!device) {
    if (gs_error[0] == '\0') {
      snprintf(gs_error, sizeof gs_error, "Embree: could not create a device: %s",
               code_name(rtcGetDeviceError(NULL)));
    }
    return NULL;
  }
  rtcSetDeviceErrorFunction(device, error_callback, NULL);
  gs_device* d = (gs_device*)malloc(sizeof *d);
  if (!d) {
    rtcReleaseDevice(device);
    set_error("out of memory");
    return NULL;
  }
  d->device = device;
  return d;
}

void gs_device_free(gs_device* device) {
  if (!device) return;
  rtcReleaseDevice(device->device);
  free(device);
}

gs_scene* gs_scene_new(gs_device* device, gs_build_mode mode, const float* verts, size_t nverts,
                       const uint32_t* tris, size_t ntris) {
  gs_error[0] = '\0';
  RTCDevice dev = device->device;
  RTCScene scene = rtcNewScene(dev);
  if (!scene) {
    check(dev, "scene creation");
    return NULL;
  }
  switch (mode) {
    case GS_BUILD_STATIC:
      rtcSetSceneBuildQuality(scene, RTC_BUILD_QUALITY_HIGH);
      rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST);
      break;
    case GS_BUILD_REBUILD:
      rtcSetSceneBuildQuality(scene, RTC_BUILD_QUALITY_MEDIUM);
      rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST);
      break;
    case GS_BUILD_REFIT:
      rtcSetSceneBuildQuality(scene, RTC_BUILD_QUALITY_LOW);
      rtcSetSceneFlags(scene, RTC_SCENE_FLAG_DYNAMIC | RTC_SCENE_FLAG_ROBUST);
      break;
  }
  RTCGeometry geom = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_TRIANGLE);
  if (!geom) {
    check(dev, "geometry creation");
    rtcReleaseScene(scene);
    return NULL;
  }
  rtcSetGeometryBuildQuality(geom, mode == GS_BUILD_REFIT ? RTC_BUILD_QUALITY_REFIT
                                   : mode == GS_BUILD_STATIC ? RTC_BUILD_QUALITY_HIGH
                                                              : RTC_BUILD_QUALITY_MEDIUM);
  /* Embree reads 16 bytes at the last vertex: its buffers are padded by rtcSetNewGeometryBuffer. */
  float* vb = (float*)rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                              3 * sizeof(float), nverts);
  uint32_t* ib = (uint32_t*)rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0,
                                                    RTC_FORMAT_UINT3, 3 * sizeof(uint32_t), ntris);
  if (!vb || !ib || check(dev, "buffer allocation")) {
    rtcReleaseGeometry(geom);
    rtcReleaseScene(scene);
    if (gs_error[0] == '\0') set_error("Embree: could not allocate geometry buffers");
    return NULL;
  }
  memcpy(vb, verts, nverts * 3 * sizeof(float));
  memcpy(ib, tris, ntris * 3 * sizeof(uint32_t));
  rtcCommitGeometry(geom);
  rtcAttachGeometryByID(scene, geom, 0);
  rtcCommitScene(scene);
  if (check(dev, "scene commit")) {
    rtcReleaseGeometry(geom);
    rtcReleaseScene(scene);
    return NULL;
  }
  gs_scene* s = (gs_scene*)malloc(sizeof *s);
  if (!s) {
    rtcReleaseGeometry(geom);
    rtcReleaseScene(scene);
    set_error("out of memory");
    return NULL;
  }
  s->device = dev;
  s->scene = scene;
  s->geom = geom;
  s->vbuf = vb;
  s->nverts = nverts;
  s->ntris = ntris;
  return s;
}

int gs_scene_update_vertices(gs_scene* s, const float* verts, size_t nverts) {
  gs_error[0] = '\0';
  if (nverts != s->nverts) {
    snprintf(gs_error, sizeof gs_error,
             "vertex update with %zu vertices for a scene of %zu vertices", nverts, s->nverts);
    return -1;
  }
  memcpy(s->vbuf, verts, nverts * 3 * sizeof(float));
  rtcUpdateGeometryBuffer(s->geom, RTC_BUFFER_TYPE_VERTEX, 0);
  rtcCommitGeometry(s->geom);
  rtcCommitScene(s->scene);
  return check(s->device, "scene update");
}

void gs_scene_free(gs_scene* s) {
  if (!s) return;
  rtcReleaseGeometry(s->geom);
  rtcReleaseScene(s->scene);
  free(s);
}

static void fill_hit(gs_hit* h, float t, float u, float v, unsigned geom, unsigned prim) {
  if (geom == RTC_INVALID_GEOMETRY_ID) {
    h->t = INFINITY;
    h->u = 0.0f;
    h->v = 0.0f;
    h->prim = GS_INVALID_ID;
  } else {
    h->t = t;
    h->u = u;
    h->v = v;
    h->prim = prim;
  }
}

/* Embree's ray from ours: every mask bit, time 0. */
static void fill_ray1(struct RTCRay* ray, const gs_ray* r) {
  ray->org_x = r->org[0];
  ray->org_y = r->org[1];
  ray->org_z = r->org[2];
  ray->tnear = r->tnear;
  ray->dir_x = r->dir[0];
  ray->dir_y = r->dir[1];
  ray->dir_z = r->dir[2];
  ray->time = 0.0f;
  ray->tfar = r->tfar;
  ray->mask = 0xFFFFFFFFu;
  ray->id = 0;
  ray->flags = 0;
}

/* A packet of Embree's rays from our first `count` (at most 8) rays; the lanes past `count`
 * repeat the first ray and are marked invalid. */
static void fill_ray8(struct RTCRay8* ray, int* valid, const gs_ray* r, size_t count) {
  for (size_t i = 0; i < 8; i++) {
    const gs_ray* ri = &r[i < count ? i : 0];
    valid[i] = i < count ? -1 : 0;
    ray->org_x[i] = ri->org[0];
    ray->org_y[i] = ri->org[1];
    ray->org_z[i] = ri->org[2];
    ray->tnear[i] = ri->tnear;
    ray->dir_x[i] = ri->dir[0];
    ray->dir_y[i] = ri->dir[1];
    ray->dir_z[i] = ri->dir[2];
    ray->time[i] = 0.0f;
    ray->tfar[i] = ri->tfar;
    ray->mask[i] = 0xFFFFFFFFu;
    ray->id[i] = (unsigned)i;
    ray->flags[i] = 0;
  }
}

static void intersect1(const gs_scene* s, const gs_ray* r, gs_hit* h) {
  struct RTCRayHit rh;
  fill_ray1(&rh.ray, r);
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
#if GS_EMBREE4
  struct RTCIntersectArguments args;
  rtcInitIntersectArguments(&args);
  rtcIntersect1(s->scene, &rh, &args);
#else
  struct RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  rtcIntersect1(s->scene, &ctx, &rh);
#endif
  fill_hit(h, rh.ray.tfar, rh.hit.u, rh.hit.v, rh.hit.geomID, rh.hit.primID);
}

static void intersect8(const gs_scene* s, const gs_ray* r, gs_hit* h, size_t count) {
  struct RTCRayHit8 rh;
  int valid[8];
  fill_ray8(&rh.ray, valid, r, count);
  for (size_t i = 0; i < 8; i++) {
    rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
  }
#if GS_EMBREE4
  struct RTCIntersectArguments args;
  rtcInitIntersectArguments(&args);
  args.flags = RTC_RAY_QUERY_FLAG_COHERENT;
  rtcIntersect8(valid, s->scene, &rh, &args);
#else
  struct RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  ctx.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
  rtcIntersect8(valid, s->scene, &ctx, &rh);
#endif
  for (size_t i = 0; i < count; i++) {
    fill_hit(&h[i], rh.ray.tfar[i], rh.hit.u[i], rh.hit.v[i], rh.hit.geomID[i], rh.hit.primID[i]);
  }
}

int gs_intersect(const gs_scene* s, const gs_ray* rays, gs_hit* hits, size_t n, int coherent) {
  gs_error[0] = '\0';
  if (coherent) {
    for (size_t i = 0; i < n; i += 8) {
      intersect8(s, rays + i, hits + i, n - i < 8 ? n - i : 8);
    }
  } else {
    for (size_t i = 0; i < n; i++) intersect1(s, &rays[i], &hits[i]);
  }
  return check(s->device, "ray query");
}

/* Whether ray r meets the surface anywhere in [tnear, tfar]: Embree stops at the first
 * triangle it finds, and sets tfar to -inf when it found one. */
static int occluded1(const gs_scene* s, const gs_ray* r) {
  struct RTCRay ray;
  fill_ray1(&ray, r);
#if GS_EMBREE4
  struct RTCOccludedArguments args;
  rtcInitOccludedArguments(&args);
  rtcOccluded1(s->scene, &ray, &args);
#else
  struct RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  rtcOccluded1(s->scene, &ctx, &ray);
#endif
  return ray.tfar == -INFINITY;
}

/* As occluded1 for up to 8 rays (count) at once, as a packet. */
static void occluded8(const gs_scene* s, const gs_ray* r, uint8_t* hit, size_t count) {
  struct RTCRay8 ray;
  int valid[8];
  fill_ray8(&ray, valid, r, count);
#if GS_EMBREE4
  struct RTCOccludedArguments args;
  rtcInitOccludedArguments(&args);
  args.flags = RTC_RAY_QUERY_FLAG_COHERENT;
  rtcOccluded8(valid, s->scene, &ray, &args);
#else
  struct RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  ctx.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
  rtcOccluded8(valid, s->scene, &ctx, &ray);
#endif
  for (size_t i = 0; i < count; i++) hit[i] = (uint8_t)(ray.tfar[i] == -INFINITY);
}

int gs_occluded(const gs_scene* s, const gs_ray* rays, uint8_t* hit, size_t n, int coherent) {
  gs_error[0] = '\0';
  if (coherent) {
    for (size_t i = 0; i < n; i += 8) occluded8(s, rays + i, hit + i, n - i < 8 ? n - i : 8);
  } else {
    for (size_t i = 0; i < n; i++) hit[i] = (uint8_t)occluded1(s, &rays[i]);
  }
  return check(s->device, "occlusion query");
}

/* ---- closest point queries ---- */

typedef struct closest_ctx {
  const double* verts;
  const uint32_t* tris;
  double p[3];
  double best_d2;
  double best[3];
  uint32_t prim;
} closest_ctx;

static double dot3(const double* a, const double* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

static void sub3(double* r, const double* a, const double* b) {
  r[0] = a[0] - b[0];
  r[1] = a[1] - b[1];
  r[2] = a[2] - b[2];
}

static void lerp_out(double* out, const double* a, const double* ab, const double* ac, double s,
                     double t) {
  for (int k = 0; k < 3; k++) out[k] = a[k] + s * ab[k] + t * ac[k];
}

/* Closest point on triangle abc to p (Ericson, Real-Time Collision Detection, 5.1.5). */
static void closest_on_triangle(double* out, const double* p, const double* a, const double* b,
                                const double* c) {
  double ab[3], ac[3], ap[3], bp[3], cp[3];
  sub3(ab, b, a);
  sub3(ac, c, a);
  sub3(ap, p, a);
  double d1 = dot3(ab, ap), d2 = dot3(ac, ap);
  if (d1 <= 0.0 && d2 <= 0.0) {
    memcpy(out, a, 3 * sizeof(double));
    return;
  }
  sub3(bp, p, b);
  double d3 = dot3(ab, bp), d4 = dot3(ac, bp);
  if (d3 >= 0.0 && d4 <= d3) {
    memcpy(out, b, 3 * sizeof(double));
    return;
  }
  double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {
    double v = d1 / (d1 - d3);
    lerp_out(out, a, ab, ac, v, 0.0);
    return;
  }
  sub3(cp, p, c);
  double d5 = dot3(ab, cp), d6 = dot3(ac, cp);
  if (d6 >= 0.0 && d5 <= d6) {
    memcpy(out, c, 3 * sizeof(double));
    return;
  }
  double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {
    double w = d2 / (d2 - d6);
    lerp_out(out, a, ab, ac, 0.0, w);
    return;
  }
  double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
    double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    for (int k = 0; k < 3; k++) out[k] = b[k] + w * (c[k] - b[k]);
    return;
  }
  double denom = 1.0 / (va + vb + vc);
  lerp_out(out, a, ab, ac, vb * denom, vc * denom);
}

static bool closest_callback(struct RTCPointQueryFunctionArguments* args) {
  closest_ctx* ctx = (closest_ctx*)args->userPtr;
  const uint32_t* t = ctx->tris + 3 * (size_t)args->primID;
  double q[3], d[3];
  closest_on_triangle(q, ctx->p, ctx->verts + 3 * (size_t)t[0], ctx->verts + 3 * (size_t)t[1],
                      ctx->verts + 3 * (size_t)t[2]);
  sub3(d, q, ctx->p);
  double d2 = dot3(d, d);
  if (d2 < ctx->best_d2) {
    ctx->best_d2 = d2;
    memcpy(ctx->best, q, sizeof q);
    ctx->prim = args->primID;
    /* Shrink the search radius, padded so float rounding of the BVH bounds never prunes a
     * triangle that is as close in double precision. */
    args->query->radius = (float)(sqrt(d2) * (1.0 + 1e-5)) + 1e-30f;
    return true;
  }
  return false;
}

static void closest_point(const gs_scene* s, closest_ctx* ctx, float radius) {
  struct RTCPointQuery q;
  q.x = (float)ctx->p[0];
  q.y = (float)ctx->p[1];
  q.z = (float)ctx->p[2];
  q.time = 0.0f;
  q.radius = radius;
  struct RTCPointQueryContext qc;
  rtcInitPointQueryContext(&qc);
  rtcPointQuery(s->scene, &q, &qc, closest_callback, ctx);
}

int gs_closest_points(const gs_scene* s, const double* verts, const uint32_t* tris,
                      const double* points, size_t n, double radius_hint, gs_closest* out) {
  gs_error[0] = '\0';
  for (size_t i = 0; i < n; i++) {
    closest_ctx ctx;
    ctx.verts = verts;
    ctx.tris = tris;
    memcpy(ctx.p, points + 3 * i, sizeof ctx.p);
    ctx.best_d2 = INFINITY;
    ctx.prim = GS_INVALID_ID;
    closest_point(s, &ctx, (float)radius_hint);
    if (ctx.prim == GS_INVALID_ID && isfinite(radius_hint)) closest_point(s, &ctx, INFINITY);
    memcpy(out[i].point, ctx.best, sizeof ctx.best);
    out[i].dist = ctx.prim == GS_INVALID_ID ? INFINITY : sqrt(ctx.best_d2);
    out[i].prim = ctx.prim;
  }
  return check(s->device, "closest-point query");
}
