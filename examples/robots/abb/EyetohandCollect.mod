MODULE EyetohandCollect
    ! eyetohand calibration collection for ABB robots (RAPID, IRC5 / OmniCore, option PC Interface
    ! or Socket Messaging). UNTESTED on a controller: no ABB controller here (its exchange with the
    ! real server is replayed by tests/test_robot_programs.py). Read examples/robots/README.md first.
    !
    ! Vision side: eyetohand serve --tcp 0.0.0.0:5000 --camera URI --token-file FILE
    ! The token: a service on any address but loopback needs one (serve --token-file FILE or
    ! EYETOHAND_TOKEN) and the first line is then AUTH <token>: set TOKEN below to the same text (a
    ! server without a token answers AUTH with OK too). A wrong token: the program stops and says so
    ! (the server answers "ERR send 'AUTH <token>' first; closing", code -14, and closes).
    !
    ! Manual references: "Technical reference manual - RAPID Instructions, Functions and Data
    ! types" (3HAC050917), by the built-in's name; "Application manual - Controller software"
    ! (Socket Messaging).
    !
    ! Traps handled here:
    ! * A RAPID string holds at most 80 characters (data type "string"); a longer result of "+" is a
    !   run-time error (ERR_STRTOOLONG), so every message that quotes a reply cuts it (Clip) to fit.
    ! * SocketReceive \Str takes at most 80 bytes and leaves the rest of a longer reply in the socket,
    !   where it would be read as the NEXT reply: ReadLine reads byte by byte up to LF
    !   (\ReadNoOfBytes:=1), keeps the first 80 characters and drops the rest.
    ! * Replies end with LF (a CR before it is dropped); commands are sent with CR LF.
    ! * StrPart(s, ChPos, Len) is an error past the end of s, and s + "pad" may pass 80: every
    !   prefix test goes through Clip, which never reads past the end nor builds a longer string.
    ! * StrToVal is used only on NEXT's x,y,z: END's reply starts with the model's name
    !   ("OK homography-radial,25,...") and is only displayed (the calibration is already saved).
    ! * SocketReceive waits 60 s by default and then raises ERR_SOCK_TIMEOUT: \Time:=30 here, and the
    !   ERROR handler turns a timeout into a stop with a message instead of a hanging program.
    ! * NumToStr gives a "." decimal point whatever the FlexPendant's language.
    ! * MoveL ... fine: the robot stops exactly on the point before the POINT command (a zone would
    !   let the program run ahead while the robot is still moving).

    CONST string HOST := "192.168.125.10";   ! the vision PC
    CONST num PORT := 5000;
    CONST string TOKEN := "change-me-eyetohand";   ! the vision side's token (at most 73 characters)
    CONST string BEGIN_CMD := "CAL BEGIN cell1,grid:5x5,0,570,70,650,150";
    CONST num TIMEOUT_S := 30;
    PERS tooldata tCalTarget := [TRUE, [[0, 0, 120], [1, 0, 0, 0]], [0.5, [0, 0, 50], [1, 0, 0, 0], 0, 0, 0]];
    PERS wobjdata wCal := [FALSE, TRUE, "", [[0, 0, 0], [1, 0, 0, 0]], [[0, 0, 0], [1, 0, 0, 0]]];

    VAR socketdev sock;
    VAR string reply;
    VAR num vals{3};

    PROC main()
        VAR robtarget p;
        VAR string cmd;
        SocketClose sock;                              ! SocketClose
        SocketCreate sock;                             ! SocketCreate
        SocketConnect sock, HOST, PORT \Time:=10;      ! SocketConnect
        ! the first line: AUTH <token>; a wrong token gets "ERR send 'AUTH <token>' first; closing"
        IF NOT Command("AUTH " + TOKEN) THEN
            IF Clip(reply, 8) = "ERR send" StopCal("the vision PC refused the token (AUTH): set TOKEN");
            StopCal(reply);
        ENDIF
        IF NOT Command(BEGIN_CMD) StopCal(reply);
        p := CRobT(\Tool:=tCalTarget \WObj:=wCal);     ! CRobT
        WHILE TRUE DO
            IF NOT Command("CAL NEXT") StopCal(reply);
            IF reply = "OK DONE" GOTO done;
            IF NOT ParseXYZ(reply) StopCal("CAL NEXT: no x,y,z in " + Clip(reply, 52));
            p.trans := [vals{1}, vals{2}, vals{3}];
            MoveL p, v100, fine, tCalTarget \WObj:=wCal;   ! MoveL, zonedata fine
            WaitTime 0.5;
            ! NumToStr(val, dec)
            cmd := "CAL POINT " + NumToStr(vals{1}, 4) + "," + NumToStr(vals{2}, 4) + ","
                   + NumToStr(vals{3}, 4);
            IF NOT Command(cmd) THEN
                IF Clip(reply, 10) = "ERR moving" THEN
                    WaitTime 1;
                    IF NOT Command(cmd) TPWrite "eyetohand: point skipped: " + Clip(reply, 54);
                ELSE
                    TPWrite "eyetohand: point skipped: " + Clip(reply, 54);   ! TPWrite: 80 chars
                ENDIF
            ENDIF
        ENDWHILE
        done:
        IF NOT Command("CAL END") StopCal(reply);
        TPWrite "eyetohand: calibrated: " + Clip(reply, 57);
        SocketClose sock;
    ERROR
        IF ERRNO = ERR_SOCK_TIMEOUT THEN
            TPWrite "eyetohand: no answer from the vision PC within the timeout";
        ELSEIF ERRNO = ERR_SOCK_CLOSED THEN
            TPWrite "eyetohand: the vision PC closed the connection";
        ENDIF
        SocketClose sock;
        Stop;
    ENDPROC

    PROC StopCal(string why)
        TPWrite "eyetohand: stopped: " + Clip(why, 60);
        SocketClose sock;
        Stop;
    ENDPROC

    ! The first n characters of s (all of s when it is shorter): keeps "prefix + reply" within 80.
    FUNC string Clip(string s, num n)
        IF StrLen(s) <= n RETURN s;                    ! StrLen
        RETURN StrPart(s, 1, n);                       ! StrPart(Str, ChPos, Len): within s
    ENDFUNC

    ! Send one command (CR LF), read the reply into reply; TRUE when it starts with OK.
    FUNC bool Command(string cmd)
        SocketSend sock \Str:=cmd + "\0D\0A";          ! SocketSend \Str; "\0D\0A": string, hex escape
        reply := ReadLine();
        RETURN Clip(reply, 2) = "OK";
    ENDFUNC

    FUNC string ReadLine()
        VAR string line := "";
        VAR string ch;
        WHILE TRUE DO
            ! SocketReceive \Str \ReadNoOfBytes \Time
            SocketReceive sock \Str:=ch \ReadNoOfBytes:=1 \Time:=TIMEOUT_S;
            IF ch = "\0A" RETURN line;
            IF ch <> "\0D" AND StrLen(line) < 80 line := line + ch;
        ENDWHILE
    ENDFUNC

    ! NEXT's "OK x,y,z" into vals{1..3}: TRUE when there are exactly three numbers.
    FUNC bool ParseXYZ(string text)
        VAR num start := 4;
        VAR num comma;
        VAR num n := 0;
        IF Clip(text, 3) <> "OK " RETURN FALSE;
        WHILE start <= StrLen(text) DO
            comma := StrFind(text, start, ",");         ! StrFind: StrLen + 1 when not found
            Incr n;
            IF n > 3 OR comma = start RETURN FALSE;
            IF NOT StrToVal(StrPart(text, start, comma - start), vals{n}) RETURN FALSE;   ! StrToVal
            start := comma + 1;
        ENDWHILE
        RETURN n = 3;
    ENDFUNC
ENDMODULE
