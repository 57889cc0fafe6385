// Several avatars in one session (rooms, DESIGN.md "Rooms and scale-out"; the reference server does not
// implement them yet): the newest-frame handoff per member between the receive thread and the main
// thread, and the room events the main thread spawns and removes renderers from. UnityEngine-free, C# 7.2.
using System.Collections.Generic;

namespace Ofera.Client
{
    public enum RoomEventKind { Joined, Left }

    /// <summary>A member whose avatar is complete (Joined: spawn a renderer) or who left (Left: remove it).</summary>
    public sealed class RoomEvent
    {
        public RoomEventKind Kind;
        public string Member;
        /// <summary>Joined: the member's static avatar (session coordinates); Left: null.</summary>
        public AvatarData Avatar;
        public JoinMessage Join;
        /// <summary>Joined: the session's welcome with this member's avatar (what a sink's SetAvatar needs).</summary>
        public Welcome Welcome;
        /// <summary>Left: the server's reason (may be null).</summary>
        public string Reason;
        /// <summary>Session number (OferaClient.SessionNumber) the event belongs to; members of older sessions are gone.</summary>
        public int Session;

        public override string ToString() { return Kind + " " + Member + (Reason != null ? " (" + Reason + ")" : ""); }
    }

    /// <summary>
    /// Newest-wins frame handoff, one slot per member (null: the session's own avatar, v1), sharing one
    /// pool of <see cref="FrameData"/>. The receive thread decodes into <see cref="DecodeTarget"/> and
    /// calls <see cref="Publish"/>; the main thread calls <see cref="Take"/>, and the frame it gets stays
    /// valid until its next Take for that member. No allocation once every slot has its frames.
    /// </summary>
    public sealed class FrameExchange
    {
        sealed class Slot
        {
            public FrameData Ready, Held;
        }

        readonly object _lock = new object();
        readonly Stack<FrameData> _pool = new Stack<FrameData>();
        readonly Dictionary<string, Slot> _members = new Dictionary<string, Slot>();
        readonly Slot _own = new Slot();
        FrameData _rx = new FrameData();

        /// <summary>Receive thread only: the container the next frame is decoded into.</summary>
        public FrameData DecodeTarget { get { return _rx; } }

        /// <summary>Frames currently pooled (tests).</summary>
        public int Pooled { get { lock (_lock) return _pool.Count; } }

        /// <summary>Receive thread: hands the frame in DecodeTarget to its member's slot. True if an untaken frame was replaced (dropped).</summary>
        public bool Publish(string member)
        {
            lock (_lock)
            {
                Slot s = SlotFor(member, true);
                bool dropped = s.Ready != null;
                FrameData next = dropped ? s.Ready : _pool.Count > 0 ? _pool.Pop() : new FrameData();
                s.Ready = _rx;
                _rx = next;
                return dropped;
            }
        }

        /// <summary>Receive thread: whether the member's slot holds a frame the main thread has not taken (the next
        /// Publish would replace it).</summary>
        public bool HasUntaken(string member)
        {
            lock (_lock)
            {
                Slot s = SlotFor(member, false);
                return s != null && s.Ready != null;
            }
        }

        /// <summary>Main thread: the member's newest frame not taken yet, or null. Recycles the one taken before.</summary>
        public FrameData Take(string member)
        {
            lock (_lock)
            {
                Slot s = SlotFor(member, false);
                if (s == null) return null;
                if (s.Held != null) { _pool.Push(s.Held); s.Held = null; }
                if (s.Ready == null) return null;
                s.Held = s.Ready;
                s.Ready = null;
                return s.Held;
            }
        }

        /// <summary>Receive thread, on leave: forgets the member (its untaken frame returns to the pool; the main thread may finish with the one it holds).</summary>
        public void Drop(string member)
        {
            lock (_lock)
            {
                Slot s;
                if (member == null || !_members.TryGetValue(member, out s)) return;
                if (s.Ready != null) _pool.Push(s.Ready);
                _members.Remove(member);
            }
        }

        /// <summary>New session: untaken frames of every slot return to the pool; members are forgotten.</summary>
        public void Reset()
        {
            lock (_lock)
            {
                if (_own.Ready != null) { _pool.Push(_own.Ready); _own.Ready = null; }
                foreach (KeyValuePair<string, Slot> kv in _members)
                    if (kv.Value.Ready != null) _pool.Push(kv.Value.Ready);
                _members.Clear();
            }
        }

        Slot SlotFor(string member, bool create)
        {
            if (member == null) return _own;
            Slot s;
            if (_members.TryGetValue(member, out s)) return s;
            if (!create) return null;
            s = new Slot();
            _members[member] = s;
            return s;
        }
    }
}
