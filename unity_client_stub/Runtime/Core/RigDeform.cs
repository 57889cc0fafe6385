// Expression streaming ("params" encoding, PROTOCOL.md 13.4): the plain C# reference of the client-side
// deformation. From a rig (RigData, decoded from the `rig` messages) and one frame's 68 params it computes what
// ofera_protocol/rig.py's deform_rig computes, formula for formula, in float64, and writes the rig's Gaussians'
// float32 position, rotation (x, y, z, w) and scale in FLAME space. The GPU twin is
// Runtime/Unity/Shaders/OferaRigDeform.compute (float32). UnityEngine-free, C# 7.2.
using System;

namespace Ofera.Client
{
    /// <summary>
    /// One deformation state per stream (scratch buffers; not thread-safe). Per frame (PROTOCOL.md 13.4):
    ///   expr = params[0..E); R_jaw, R_leye, R_reye from their 6D (pytorch3d rows, Gram-Schmidt), root and neck I;
    ///   J = joints + joints_expr . expr;  A_k = [R_k | J_k - R_k J_k];
    ///   v_po = template + expr_basis . expr + pose_basis . (R - I)[pose_rows];  v = (sum_k W_k A_k) [v_po; 1];
    ///   per face: R_f = [a0 | a1 | a2], s_f, centroid c_f, quat(R_f) (w >= 0, best-conditioned branch);
    ///   per Gaussian: triangle R_f (p s_f) + c_f, barycentric sum b_k v_k + (e1 x e2) offset;
    ///   rotation normalize(quat(R_f) (x) normalize(q)); scale local_scale s_f.
    /// </summary>
    public sealed class RigDeformer
    {
        const double Eps2 = 1e-20;
        const int J = ParamsProtocol.Joints;
        const int FaceStride = 17; // R (9, row-major), q (w, x, y, z), s_f, c_f (3)
        public readonly RigData Rig;
        readonly double[] _expr, _rot = new double[9 * J], _a = new double[12 * J], _coef, _verts, _face;
        readonly double[] _local; // M x 4 normalize(local_rotation) (x, y, z, w): the same every frame

        public RigDeformer(RigData rig)
        {
            if (rig == null) throw new ArgumentNullException("rig");
            if (rig.ExprDims > ParamsProtocol.ExprValues)
                throw new ArgumentException("the rig has " + rig.ExprDims + " expression components; params carry " + ParamsProtocol.ExprValues);
            Rig = rig;
            _expr = new double[rig.ExprDims];
            _coef = new double[rig.PoseCount];
            _verts = new double[3 * rig.Vertices];
            _face = new double[FaceStride * rig.Faces];
            _local = new double[4 * rig.Gaussians];
            float[] lr = rig.LocalRotation;
            for (int m = 0; m < rig.Gaussians; m++)
            {
                double x = lr[4 * m], y = lr[4 * m + 1], z = lr[4 * m + 2], w = lr[4 * m + 3];
                double n = Math.Max(Math.Sqrt(x * x + y * y + z * z + w * w), 1e-12);
                _local[4 * m] = x / n; _local[4 * m + 1] = y / n; _local[4 * m + 2] = z / n; _local[4 * m + 3] = w / n;
            }
        }

        /// <summary>The deformed rig vertices (S x 3, metres, FLAME space) of the last <see cref="Deform"/> call.</summary>
        public double[] Vertices { get { return _verts; } }

        /// <summary>
        /// 68 params (from <paramref name="offset"/>) -> the rig's Gaussians, in rig order (session ids Rig.Index):
        /// position (3 M), rotation (4 M, x y z w) and scale (3 M) float32, written from index 0.
        /// </summary>
        public void Deform(float[] values, int offset, float[] position, float[] rotation, float[] scale)
        {
            RigData r = Rig;
            if (values == null || values.Length < offset + ParamsProtocol.Length)
                throw new ArgumentException("params need " + ParamsProtocol.Length + " values");
            int m = r.Gaussians;
            if (position.Length < 3 * m || rotation.Length < 4 * m || scale.Length < 3 * m)
                throw new ArgumentException("output arrays are smaller than the rig's " + m + " Gaussians");
            Pose(values, offset);
            Skin();
            Faces();
            Gaussians(position, rotation, scale);
        }

        /// <summary>expr, joint rotations, skinning transforms A_k and pose-corrective coefficients.</summary>
        void Pose(float[] y, int offset)
        {
            RigData r = Rig;
            int e = r.ExprDims;
            for (int j = 0; j < e; j++) _expr[j] = y[offset + j];
            for (int k = 0; k < J; k++)
                for (int i = 0; i < 9; i++) _rot[9 * k + i] = (i % 4 == 0) ? 1.0 : 0.0;
            for (int k = 0; k < 3; k++)
            {
                int o = offset + ParamsProtocol.ExprValues + 6 * k;
                double a1x = y[o], a1y = y[o + 1], a1z = y[o + 2], a2x = y[o + 3], a2y = y[o + 4], a2z = y[o + 5];
                double n = Math.Max(Math.Sqrt(a1x * a1x + a1y * a1y + a1z * a1z), 1e-12);
                double b1x = a1x / n, b1y = a1y / n, b1z = a1z / n;
                double d = b1x * a2x + b1y * a2y + b1z * a2z;
                double cx = a2x - d * b1x, cy = a2y - d * b1y, cz = a2z - d * b1z;
                n = Math.Max(Math.Sqrt(cx * cx + cy * cy + cz * cz), 1e-12);
                double b2x = cx / n, b2y = cy / n, b2z = cz / n;
                int q = 9 * (k + 2);
                _rot[q] = b1x; _rot[q + 1] = b1y; _rot[q + 2] = b1z;
                _rot[q + 3] = b2x; _rot[q + 4] = b2y; _rot[q + 5] = b2z;
                _rot[q + 6] = b1y * b2z - b1z * b2y;
                _rot[q + 7] = b1z * b2x - b1x * b2z;
                _rot[q + 8] = b1x * b2y - b1y * b2x;
            }
            for (int k = 0; k < J; k++)
            {
                double j0 = r.Joints[3 * k], j1 = r.Joints[3 * k + 1], j2 = r.Joints[3 * k + 2];
                for (int c = 0; c < e; c++)
                {
                    double x = _expr[c];
                    j0 += r.JointsExpr[(3 * k) * e + c] * x;
                    j1 += r.JointsExpr[(3 * k + 1) * e + c] * x;
                    j2 += r.JointsExpr[(3 * k + 2) * e + c] * x;
                }
                for (int i = 0; i < 3; i++)
                {
                    int ro = 9 * k + 3 * i, ao = 12 * k + 4 * i;
                    _a[ao] = _rot[ro]; _a[ao + 1] = _rot[ro + 1]; _a[ao + 2] = _rot[ro + 2];
                    double ji = i == 0 ? j0 : i == 1 ? j1 : j2;
                    _a[ao + 3] = ji - (_rot[ro] * j0 + _rot[ro + 1] * j1 + _rot[ro + 2] * j2);
                }
            }
            for (int p = 0; p < r.PoseCount; p++)
            {
                int row = r.PoseRows[p];
                int k = 1 + row / 9, i = (row % 9) / 3, c = row % 3;
                _coef[p] = _rot[9 * k + 3 * i + c] - (i == c ? 1.0 : 0.0);
            }
        }

        /// <summary>Blend shapes and skinning of every rig vertex -> _verts.</summary>
        void Skin()
        {
            RigData r = Rig;
            int e = r.ExprDims, pc = r.PoseCount;
            float[] eb = r.ExprBasis, pb = r.PoseBasis, w = r.Weights, t = r.Template;
            for (int s = 0; s < r.Vertices; s++)
            {
                double p0 = t[3 * s], p1 = t[3 * s + 1], p2 = t[3 * s + 2];
                int o = s * e * 3;
                for (int j = 0; j < e; j++, o += 3)
                {
                    double x = _expr[j];
                    p0 += eb[o] * x; p1 += eb[o + 1] * x; p2 += eb[o + 2] * x;
                }
                o = s * pc * 3;
                for (int j = 0; j < pc; j++, o += 3)
                {
                    double x = _coef[j];
                    p0 += pb[o] * x; p1 += pb[o + 1] * x; p2 += pb[o + 2] * x;
                }
                for (int i = 0; i < 3; i++)
                {
                    double t0 = 0, t1 = 0, t2 = 0, t3 = 0;
                    for (int k = 0; k < J; k++)
                    {
                        double wk = w[J * s + k];
                        int a = 12 * k + 4 * i;
                        t0 += wk * _a[a]; t1 += wk * _a[a + 1]; t2 += wk * _a[a + 2]; t3 += wk * _a[a + 3];
                    }
                    _verts[3 * s + i] = t0 * p0 + t1 * p1 + t2 * p2 + t3;
                }
            }
        }

        /// <summary>Per rig face: R_f (columns a0, a1, a2), its quaternion (w >= 0), s_f, centroid.</summary>
        void Faces()
        {
            RigData r = Rig;
            double[] v = _verts, o = _face;
            for (int u = 0; u < r.Faces; u++)
            {
                int i0 = 3 * r.Face[3 * u], i1 = 3 * r.Face[3 * u + 1], i2 = 3 * r.Face[3 * u + 2];
                double v0x = v[i0], v0y = v[i0 + 1], v0z = v[i0 + 2];
                double e1x = v[i1] - v0x, e1y = v[i1 + 1] - v0y, e1z = v[i1 + 2] - v0z;
                double e2x = v[i2] - v0x, e2y = v[i2 + 1] - v0y, e2z = v[i2 + 2] - v0z;
                double ll = Math.Sqrt(Math.Max(e1x * e1x + e1y * e1y + e1z * e1z, Eps2));
                double a0x = e1x / ll, a0y = e1y / ll, a0z = e1z / ll;
                double cx = a0y * e2z - a0z * e2y, cy = a0z * e2x - a0x * e2z, cz = a0x * e2y - a0y * e2x;
                double cl = Math.Sqrt(Math.Max(cx * cx + cy * cy + cz * cz, Eps2));
                double a1x = cx / cl, a1y = cy / cl, a1z = cz / cl;
                double a2x = a0y * a1z - a0z * a1y, a2y = a0z * a1x - a0x * a1z, a2z = a0x * a1y - a0y * a1x;
                int f = FaceStride * u;
                o[f] = a0x; o[f + 1] = a1x; o[f + 2] = a2x;
                o[f + 3] = a0y; o[f + 4] = a1y; o[f + 5] = a2y;
                o[f + 6] = a0z; o[f + 7] = a1z; o[f + 8] = a2z;
                // matrix_to_quaternion: the branch of the largest 4 q_i^2 (the first on ties); R[i, j] is a_j[i]
                double sq0 = 1 + a0x + a1y + a2z, sq1 = 1 + a0x - a1y - a2z, sq2 = 1 - a0x + a1y - a2z, sq3 = 1 - a0x - a1y + a2z;
                double d21 = a1z - a2y, d02 = a2x - a0z, d10 = a0y - a1x;
                double s21 = a1z + a2y, s02 = a2x + a0z, s10 = a0y + a1x;
                int best = 0;
                double top = sq0;
                if (sq1 > top) { best = 1; top = sq1; }
                if (sq2 > top) { best = 2; top = sq2; }
                if (sq3 > top) best = 3;
                double qw, qx, qy, qz;
                if (best == 0) { qw = sq0; qx = d21; qy = d02; qz = d10; }
                else if (best == 1) { qw = d21; qx = sq1; qy = s10; qz = s02; }
                else if (best == 2) { qw = d02; qx = s10; qy = sq2; qz = s21; }
                else { qw = d10; qx = s02; qy = s21; qz = sq3; }
                double qn = Math.Sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
                if (qw / qn < 0) qn = -qn;
                o[f + 9] = qw / qn; o[f + 10] = qx / qn; o[f + 11] = qy / qn; o[f + 12] = qz / qn;
                o[f + 13] = (ll + Math.Abs(a2x * e2x + a2y * e2y + a2z * e2z)) / 2;
                o[f + 14] = (v0x + v[i1] + v[i2]) / 3.0;
                o[f + 15] = (v0y + v[i1 + 1] + v[i2 + 1]) / 3.0;
                o[f + 16] = (v0z + v[i1 + 2] + v[i2 + 2]) / 3.0;
            }
        }

        void Gaussians(float[] position, float[] rotation, float[] scale)
        {
            RigData r = Rig;
            double[] o = _face, v = _verts;
            float[] lp = r.Local, ls = r.LocalScale;
            double[] lr = _local;
            bool tri = r.Binding == RigBinding.Triangle;
            for (int m = 0; m < r.Gaussians; m++)
            {
                int u = r.GaussianFace[m], f = FaceStride * u;
                double s = o[f + 13];
                if (tri)
                {
                    double px = lp[3 * m] * s, py = lp[3 * m + 1] * s, pz = lp[3 * m + 2] * s;
                    position[3 * m] = (float)(o[f] * px + o[f + 1] * py + o[f + 2] * pz + o[f + 14]);
                    position[3 * m + 1] = (float)(o[f + 3] * px + o[f + 4] * py + o[f + 5] * pz + o[f + 15]);
                    position[3 * m + 2] = (float)(o[f + 6] * px + o[f + 7] * py + o[f + 8] * pz + o[f + 16]);
                }
                else
                {
                    int i0 = 3 * r.Face[3 * u], i1 = 3 * r.Face[3 * u + 1], i2 = 3 * r.Face[3 * u + 2];
                    double e1x = v[i1] - v[i0], e1y = v[i1 + 1] - v[i0 + 1], e1z = v[i1 + 2] - v[i0 + 2];
                    double e2x = v[i2] - v[i0], e2y = v[i2 + 1] - v[i0 + 1], e2z = v[i2 + 2] - v[i0 + 2];
                    double b0 = lp[3 * m], b1 = lp[3 * m + 1], b2 = lp[3 * m + 2], off = r.NormalOffset[m];
                    position[3 * m] = (float)(b0 * v[i0] + b1 * v[i1] + b2 * v[i2] + (e1y * e2z - e1z * e2y) * off);
                    position[3 * m + 1] = (float)(b0 * v[i0 + 1] + b1 * v[i1 + 1] + b2 * v[i2 + 1] + (e1z * e2x - e1x * e2z) * off);
                    position[3 * m + 2] = (float)(b0 * v[i0 + 2] + b1 * v[i1 + 2] + b2 * v[i2 + 2] + (e1x * e2y - e1y * e2x) * off);
                }
                // Hamilton quat(R_f) (x) normalize(local (x, y, z, w)), normalised
                double bx = lr[4 * m], by = lr[4 * m + 1], bz = lr[4 * m + 2], bw = lr[4 * m + 3];
                double aw = o[f + 9], ax = o[f + 10], ay = o[f + 11], az = o[f + 12];
                double qw = aw * bw - ax * bx - ay * by - az * bz;
                double qx = aw * bx + ax * bw + ay * bz - az * by;
                double qy = aw * by - ax * bz + ay * bw + az * bx;
                double qz = aw * bz + ax * by - ay * bx + az * bw;
                double qn = Math.Sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
                rotation[4 * m] = (float)(qx / qn);
                rotation[4 * m + 1] = (float)(qy / qn);
                rotation[4 * m + 2] = (float)(qz / qn);
                rotation[4 * m + 3] = (float)(qw / qn);
                scale[3 * m] = (float)(ls[3 * m] * s);
                scale[3 * m + 1] = (float)(ls[3 * m + 1] * s);
                scale[3 * m + 2] = (float)(ls[3 * m + 2] * s);
            }
        }
    }
    /// <summary>Params frames on the CPU: the client's own deformation written into the frame, as a sparse frame.</summary>
    public static class RigFrames
    {
        /// <summary>
        /// f.Params -> f as a sparse frame of the rig's Gaussians (Index = rig.Index, Position/Rotation/Scale deformed,
        /// mirrored in x when <paramref name="mirrorX"/>), HasValues true: GaussianState.Apply and CPU sinks take it as is.
        /// </summary>
        public static void Deform(RigDeformer d, FrameData f, bool mirrorX)
        {
            RigData r = d.Rig;
            int m = r.Gaussians;
            f.EnsureCapacity(m);
            d.Deform(f.Params, 0, f.Position, f.Rotation, f.Scale);
            Array.Copy(r.Index, f.Index, m);
            f.N = m;
            f.HasIndex = true;
            f.HasValues = true;
            if (mirrorX) Coords.MirrorX(f);
        }
    }
}
