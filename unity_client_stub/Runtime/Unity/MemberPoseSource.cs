// Head poses of room members. The protocol carries expressions only: head pose belongs to the clients
// (DESIGN.md: "the headset knows it and places the avatar"), so a remote member's head pose has to come
// from the app's own networking (Netcode, Photon, Normcore..., whatever already syncs the players'
// headsets) or from a fixed seat layout. OferaAvatarClient asks a MemberPoseSource every frame and, when
// it answers, puts that member's avatar there. Needs UnityEngine; not compiled by Tests/run.sh.
using System;
using UnityEngine;

namespace Ofera.Client.Unity
{
    /// <summary>Where a room member's head is, in world space, this frame.</summary>
    public abstract class MemberPoseSource : MonoBehaviour
    {
        /// <summary>False when the member's pose is unknown (the avatar then keeps its last placement).</summary>
        public abstract bool TryGetHeadPose(string member, out Vector3 position, out Quaternion rotation);
    }

    /// <summary>
    /// Member id -> Transform (e.g. the networked head object of that player, which your networking layer
    /// moves). Register at run time with <see cref="SetHead"/>, or list them in the inspector.
    /// </summary>
    [AddComponentMenu("OFERA/Transform Member Pose Source")]
    public sealed class TransformMemberPoseSource : MemberPoseSource
    {
        [Serializable]
        public struct Entry
        {
            public string member;
            public Transform head;
        }

        public Entry[] heads = new Entry[0];

        public void SetHead(string member, Transform head)
        {
            for (int i = 0; i < heads.Length; i++)
                if (heads[i].member == member) { heads[i].head = head; return; }
            Array.Resize(ref heads, heads.Length + 1);
            heads[heads.Length - 1] = new Entry { member = member, head = head };
        }

        public override bool TryGetHeadPose(string member, out Vector3 position, out Quaternion rotation)
        {
            for (int i = 0; i < heads.Length; i++)
            {
                if (heads[i].member != member || heads[i].head == null) continue;
                heads[i].head.GetPositionAndRotation(out position, out rotation);
                return true;
            }
            position = default(Vector3);
            rotation = Quaternion.identity;
            return false;
        }
    }
}
