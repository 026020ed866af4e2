/* The robots' ground truth in C: each arm's RobotTruth (proto/cell/v1/robot.proto), its tool pose
 * included, encoded byte for byte as protobuf's own serializer encodes it.
 *
 * The robots process publishes a truth per arm at truth_hz (100 Hz by default) whether or not
 * anything moves; built in Python (a forward kinematics through the MuJoCo bindings and numpy, then
 * a message built from six-element arrays) that was about 90 us of the packet path's core per arm
 * and truth.  Here it is one call per truth tick for the whole group (cell/robot/truthcodec.py).
 *
 * Proto3's encoding, as the Python serializer writes it: fields in number order, a scalar left out
 * when it is zero, a repeated double packed (tag, byte length, little-endian doubles) and left out
 * when empty.
 */
#include <stdint.h>
#include <string.h>

typedef void (*mj_kinematics_t)(const void *m, void *d);
typedef void (*mju_mat2quat_t)(double quat[4], const double mat[9]);

typedef struct {
    int64_t n, dof, site;           /* arms, joints per arm, the tool site's id in the model */
    const void *model;              /* the arm's mjModel */
    void *data;                     /* a scratch mjData of it, this encoder's alone */
    double *qpos;                   /* (dof) its qpos */
    const double *site_xpos, *site_xmat; /* (nsite x 3), (nsite x 9) */
    mj_kinematics_t kinematics;
    mju_mat2quat_t mat2quat;
    const int64_t *ids;             /* (n) robot ids */
} truth_t;

static uint8_t *varint(uint8_t *p, uint64_t v) {
    while (v >= 0x80) {
        *p++ = (uint8_t)(v | 0x80);
        v >>= 7;
    }
    *p++ = (uint8_t)v;
    return p;
}

static uint8_t *scalar(uint8_t *p, int field, uint64_t v) {
    if (!v)
        return p;
    *p++ = (uint8_t)(field << 3);
    return varint(p, v);
}

static uint8_t *doubles(uint8_t *p, int field, const double *v, int64_t k) {
    if (k <= 0)
        return p;
    *p++ = (uint8_t)(field << 3 | 2);
    p = varint(p, (uint64_t)k * 8);
    memcpy(p, v, (size_t)k * 8); /* (x86-64 and arm64 are little-endian, as the wire) */
    return p + k * 8;
}

/* [x, y, z, qw, qx, qy, qz] of the tool site for joints q (arm.ArmModel.tool_pose) */
void truth_pose(const truth_t *t, const double *q, double pose[7]) {
    memcpy(t->qpos, q, (size_t)t->dof * sizeof(double));
    t->kinematics(t->model, t->data);
    memcpy(pose, t->site_xpos + 3 * t->site, 3 * sizeof(double));
    t->mat2quat(pose + 3, t->site_xmat + 9 * t->site);
}

/* The most bytes one arm's RobotTruth takes: each field's tag, its longest varint, or its doubles
 * behind a length of at most 3 bytes (robot_id 5, t_ns, tick and digital_out 10, stopped 1) */
int64_t truth_bound(int64_t dof) { return 108 + 24 * dof; }

/* Every arm's RobotTruth, one after another in out; ends[i]: where arm i's ends.  The group's
 * arrays: q, qd, target (n x dof), stopped (n), digital_out (n).  Returns the bytes written, or -1
 * if cap is too small (n * truth_bound(dof) is always enough). */
int64_t truth_encode(const truth_t *t, uint64_t t_ns, uint64_t tick, const double *q, const double *qd,
                     const double *target, const uint8_t *stopped, const uint64_t *digital_out,
                     uint8_t *out, int64_t cap, int64_t *ends) {
    int64_t dof = t->dof, most = truth_bound(dof);
    uint8_t *p = out;
    for (int64_t i = 0; i < t->n; i++) {
        if ((p - out) + most > cap)
            return -1;
        double pose[7];
        truth_pose(t, q + i * dof, pose);
        p = scalar(p, 1, (uint64_t)(uint32_t)t->ids[i]);
        p = scalar(p, 2, t_ns);
        p = doubles(p, 3, q + i * dof, dof);
        p = doubles(p, 4, qd + i * dof, dof);
        p = doubles(p, 5, pose, 7);
        p = doubles(p, 6, target + i * dof, dof);
        p = scalar(p, 7, stopped[i] != 0);
        p = scalar(p, 8, tick);
        p = scalar(p, 9, digital_out[i]);
        ends[i] = p - out;
    }
    return p - out;
}
