/*
 * redistro._kernels: what every kernel file shares (see kernel_core.c).
 *
 * A kernel runs one cycle's arithmetic of an I/O path in one call. It
 * works on a Plan: named buffers (numpy arrays, shared memory) checked
 * once against the kernel's signature (argument names and element types)
 * when the plan is made. Each kernel sits in a C file beside the Python
 * module that keeps its reference (the same arithmetic in numpy):
 *
 *   kernel_core.c                  Plan, copies, seqlocks, the module
 *   plant/chassis_kernel.c         the simulated chassis (plant/chassis.py)
 *   drivers/driver_kernel.c        the robot-level driver (drivers/robot.py)
 *   esc/guard_kernel.c             the sender's guard (esc/sender.py)
 *   control/joint_kernel.c         joint PID and quintic (control/pid.py, trajectory.py)
 *   control/linalg.c               3x3 and SPD helpers (eig3, Cholesky)
 *   control/cartesian_kernel.c     the SSC's Cartesian law (control/cartesian.py)
 *   ddm/wire_kernel.c              the DDM record's crc32 and tag (ddm/record.py)
 *   ddm/step_kernel.c              a ddm's admit, emit, recv, send, reply (ddm/kernel_path.py)
 *   ddm/answer_kernel.c            a ddm's answer in the transport's thread (ddm/worker.py)
 *
 * Registers and records are packed: multi-byte values are loaded and
 * stored with memcpy (no alignment is assumed).
 */
#ifndef REDISTRO_KERNELS_H
#define REDISTRO_KERNELS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#include "kernel_layouts.h" /* generated from the declared layouts (setup.py) */

#define BARRIER() __asm__ __volatile__("" ::: "memory")

/* -- unaligned loads and stores -- */

static inline uint32_t ld_u32(const uint8_t *p) { uint32_t v; memcpy(&v, p, 4); return v; }
static inline int32_t ld_i32(const uint8_t *p) { int32_t v; memcpy(&v, p, 4); return v; }
static inline int16_t ld_i16(const uint8_t *p) { int16_t v; memcpy(&v, p, 2); return v; }
static inline uint64_t ld_u64(const uint8_t *p) { uint64_t v; memcpy(&v, p, 8); return v; }
static inline float ld_f32(const uint8_t *p) { float v; memcpy(&v, p, 4); return v; }
static inline double ld_f64(const uint8_t *p) { double v; memcpy(&v, p, 8); return v; }
static inline void st_u32(uint8_t *p, uint32_t v) { memcpy(p, &v, 4); }
static inline void st_i32(uint8_t *p, int32_t v) { memcpy(p, &v, 4); }
static inline void st_i16(uint8_t *p, int16_t v) { memcpy(p, &v, 2); }
static inline void st_u64(uint8_t *p, uint64_t v) { memcpy(p, &v, 8); }

static inline double clampd(double x, double lo, double hi) {
    return x < lo ? lo : (x > hi ? hi : x);
}

/* -- kernel signatures: argument names and element types -- */

/* An argument: its name, element type and size rule, checked when a plan
 * is made (a short or long buffer is an error there, never a read or write
 * out of bounds in a kernel):
 *   size: exactly this many elements (a record of a declared layout);
 *   row:  a multiple of this many (a table of records);
 *   dim:  per x the dimension named by this letter, the same for every
 *         argument of the kernel that names it ('j' joints, 'b' boards, ...). */
typedef struct {
    const char *name;
    char type; /* d f8, q i8, B u1 */
    int size, row;
    char dim;
    int per;
} Arg;

#define FREE(n, t) {.name = n, .type = t}
#define REC(n, t, s) {.name = n, .type = t, .size = s}
#define ROWS(n, t, r) {.name = n, .type = t, .row = r}
#define DIM(n, t, d, p) {.name = n, .type = t, .dim = d, .per = p}

typedef struct {
    const char *name;
    const Arg *args;
    int nargs;
} Signature;

#define ARGS(...) (const Arg[]){__VA_ARGS__}, (int)(sizeof((const Arg[]){__VA_ARGS__}) / sizeof(Arg))
#define MAX_ARGS 40

/* What one kernel file adds to the module: its signatures and functions. */
typedef struct {
    const Signature *signatures;
    int nsignatures;
    PyMethodDef *methods; /* ends with {NULL} */
} KernelSet;

/* -- Plan -- */

typedef struct {
    PyObject_HEAD
    const Signature *sig;
    int nargs;
    Py_buffer views[MAX_ARGS];
    uint8_t *p[MAX_ARGS];
    Py_ssize_t n[MAX_ARGS]; /* elements */
} PlanObject;

extern PyTypeObject PlanType;

/* The plan in obj, of kernel ``kernel`` (else an error is set, NULL). */
PlanObject *plan_arg(PyObject *obj, const char *kernel);

#define F64(plan, i) ((double *)(plan)->p[i])
#define I64(plan, i) ((int64_t *)(plan)->p[i])
#define U8(plan, i) ((plan)->p[i])

/* -- seqlocks (kernel_core.c) -- */

#define ATTEMPTS 4

void seqlock_write(uint8_t *seq_at, uint8_t *dst, const uint8_t *src, size_t n);
int seqlock_read(const uint8_t *seq_at, const uint8_t *src, uint8_t *dst, size_t n);
int64_t now_ns(void);
PyObject *seq_write(PyObject *mod, PyObject *arg);

/* -- the kernel files' sets -- */

extern const KernelSet CORE_KERNELS, CHASSIS_KERNELS, DRIVER_KERNELS, GUARD_KERNELS,
    JOINT_KERNELS, LINALG_KERNELS, CARTESIAN_KERNELS, WIRE_KERNELS, STEP_KERNELS;

int answer_kernel_init(PyObject *module); /* ddm/answer_kernel.c: the CompiledAnswer type */

#endif
