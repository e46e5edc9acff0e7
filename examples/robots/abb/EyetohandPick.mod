MODULE EyetohandPick
    ! eyetohand pick loop for ABB robots (RAPID, IRC5 / OmniCore, option PC Interface or Socket
    ! Messaging): LOCATE the round parts, pick each one, again. UNTESTED on a controller: no ABB
    ! controller here (its exchange with the real server is replayed by tests/test_pick_programs.py).
    ! Read examples/robots/README.md first.
    !
    ! Vision side: eyetohand serve --tcp 0.0.0.0:5000 --camera URI --calibration cell1 --token-file FILE
    ! The token: AUTH <token> first, as in EyetohandCollect.mod (TOKEN below); a wrong one stops the
    ! program with a message.
    !   LOCATE 8,12  -> OK <count>,<outside>   (parts outside the calibrated region: only counted)
    !   LOCATE NEXT  -> OK <x>,<y>,<z>,<rz>,<sigma>   or OK DONE when every part is handed out
    !
    ! Manual references: "Technical reference manual - RAPID Instructions, Functions and Data
    ! types" (3HAC050917), by the built-in's name; "Application manual - Controller software"
    ! (Socket Messaging).
    !
    ! Traps handled here (as in EyetohandCollect.mod): 80-character strings (Clip, ReadLine),
    ! SocketReceive \Time with the ERROR handler, NumToStr/StrToVal with "." decimals, MoveL ... fine
    ! (the robot stands on the part before the gripper closes). Also:
    ! * the robot must be out of the camera's view during LOCATE: it goes to pClear first.
    ! * no pick outside the calibrated region: the server never hands such a part out; a part whose
    !   sigma is above MAX_SIGMA (or unknown, -1) is skipped.
    ! * tGripper's TCP is the point the calibration's x, y, z are for; TOOL_DZ is the tool offset along
    !   z (where the gripper closes, from the part's top), APPROACH the approach/retract height.

    CONST string HOST := "192.168.125.10";   ! the vision PC
    CONST num PORT := 5000;
    CONST string TOKEN := "change-me-eyetohand";   ! the vision side's token (at most 73 characters)
    CONST string LOCATE_CMD := "LOCATE 8,12";
    CONST num TIMEOUT_S := 30;
    CONST num APPROACH := 50;
    CONST num TOOL_DZ := -2;
    CONST num MAX_SIGMA := 0.2;
    PERS tooldata tGripper := [TRUE, [[0, 0, 150], [1, 0, 0, 0]], [1, [0, 0, 60], [1, 0, 0, 0], 0, 0, 0]];
    PERS wobjdata wCal := [FALSE, TRUE, "", [[0, 0, 0], [1, 0, 0, 0]], [[0, 0, 0], [1, 0, 0, 0]]];
    CONST robtarget pClear := [[300, 200, 400], [0, 0, 1, 0], [0, 0, 0, 0], [9E9, 9E9, 9E9, 9E9, 9E9, 9E9]];
    CONST robtarget pDrop := [[300, -200, 300], [0, 0, 1, 0], [0, 0, 0, 0], [9E9, 9E9, 9E9, 9E9, 9E9, 9E9]];

    VAR socketdev sock;
    VAR string reply;
    VAR num vals{5};

    PROC main()
        VAR robtarget p;
        VAR bool more;
        SocketClose sock;                              ! SocketClose
        SocketCreate sock;                             ! SocketCreate
        SocketConnect sock, HOST, PORT \Time:=10;      ! SocketConnect
        ! the first line: AUTH <token>; a wrong token gets "ERR send 'AUTH <token>' first; closing"
        IF NOT Command("AUTH " + TOKEN) THEN
            IF Clip(reply, 8) = "ERR send" StopPick("the vision PC refused the token (AUTH): set TOKEN");
            StopPick(reply);
        ENDIF
        WHILE TRUE DO
            MoveL pClear, v500, fine, tGripper \WObj:=wCal;   ! out of the view before the picture
            IF NOT Command(LOCATE_CMD) StopPick(reply);
            IF NOT ParseNums(reply, 2) StopPick("LOCATE: no count in " + Clip(reply, 52));
            IF vals{1} = 0 THEN
                TPWrite "eyetohand: no part inside the region";
                WaitTime 1;
            ENDIF
            more := TRUE;
            WHILE more DO
                IF NOT Command("LOCATE NEXT") StopPick(reply);
                more := reply <> "OK DONE";
                IF more AND NOT ParseNums(reply, 5) StopPick("LOCATE NEXT: no pose in " + Clip(reply, 48));
                IF NOT more THEN
                    ! every part of this LOCATE handed out
                ELSEIF vals{5} < 0 OR vals{5} > MAX_SIGMA THEN
                    TPWrite "eyetohand: part skipped: " + Clip(reply, 54);
                ELSE
                    p := pClear;
                    p.trans := [vals{1}, vals{2}, vals{3} + TOOL_DZ];
                    MoveL Offs(p, 0, 0, APPROACH), v500, z10, tGripper \WObj:=wCal;   ! Offs
                    MoveL p, v100, fine, tGripper \WObj:=wCal;
                    ! close the gripper here (SetDO on your gripper's signal), then WaitTime
                    WaitTime 0.3;
                    MoveL Offs(p, 0, 0, APPROACH), v100, z10, tGripper \WObj:=wCal;
                    MoveL pDrop, v500, fine, tGripper \WObj:=wCal;
                    ! open the gripper here
                    WaitTime 0.3;
                ENDIF
            ENDWHILE
        ENDWHILE
    ERROR
        IF ERRNO = ERR_SOCK_TIMEOUT THEN
            TPWrite "eyetohand: no answer from the vision PC within the timeout";
        ELSEIF ERRNO = ERR_SOCK_CLOSED THEN
            TPWrite "eyetohand: the vision PC closed the connection";
        ENDIF
        SocketClose sock;
        Stop;
    ENDPROC

    PROC StopPick(string why)
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

    ! "OK a,b,..." into vals{1..want}: TRUE when there are exactly want numbers.
    FUNC bool ParseNums(string text, num want)
        VAR num start := 4;
        VAR num comma;
        VAR num n := 0;
        IF Clip(text, 3) <> "OK " RETURN FALSE;
        WHILE start <= StrLen(text) DO
            comma := StrFind(text, start, ",");         ! StrFind: StrLen + 1 when not found
            Incr n;
            IF n > want OR comma = start RETURN FALSE;
            IF NOT StrToVal(StrPart(text, start, comma - start), vals{n}) RETURN FALSE;   ! StrToVal
            start := comma + 1;
        ENDWHILE
        RETURN n = want;
    ENDFUNC
ENDMODULE
